"""Build hook: ship ``sb3_cql-zoo.pth`` at the top of site-packages, beside the packages (setup.cfg has the rest).

The ``.pth`` file's one line installs :mod:`sb3_cql.zoo.hook` at interpreter start-up, which registers CQL, the
tasks and our hyperparameters with RL-Zoo3 when, and only when, the zoo is imported.
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

PTH_FILE = "sb3_cql-zoo.pth"


class BuildPyWithPth(build_py):
    """``build_py`` that also puts the ``.pth`` file at the root of the wheel, editable wheels included."""

    def run(self) -> None:
        super().run()
        self.copy_file(str(Path(__file__).parent / PTH_FILE), str(self._pth_target()))

    def _pth_target(self) -> Path:
        # An editable wheel (pip install -e) is assembled from install_lib, not build_lib (setuptools' editable_wheel).
        root = self.get_finalized_command("install").install_lib if self.editable_mode else self.build_lib
        return Path(root) / PTH_FILE


setup(cmdclass={"build_py": BuildPyWithPth})
