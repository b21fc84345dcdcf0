"""Extend RL-Zoo3's modules with :func:`sb3_cql.zoo.plugin.extend` right after they are imported, in any process.

Imported at start-up by ``sb3_cql-zoo.pth``: it must stay cheap (``sys`` only, no torch, no zoo). A plain class with
``find_spec`` is a valid meta path finder; subclassing ``importlib.abc.MetaPathFinder`` would import more.
"""

from __future__ import annotations

import sys

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing at start-up
if TYPE_CHECKING:
    from importlib.machinery import ModuleSpec
    from types import ModuleType

#: The zoo modules the plugin extends, each right after it is imported (:func:`sb3_cql.zoo.plugin.extend`):
#: ``ALGOS`` and the env registry (utils), the CQL search space (hyperparams_opt), our config files (exp_manager).
TRIGGERS = ("rl_zoo3.utils", "rl_zoo3.hyperparams_opt", "rl_zoo3.exp_manager")


class ZooImportHook:
    """A meta path finder that finds nothing itself: for the :data:`TRIGGERS` it lets the other finders find the
    module and wraps its loader, so that the plugin extends the module as soon as it has executed."""

    def find_spec(self, fullname: str, path=None, target: ModuleType | None = None) -> ModuleSpec | None:
        if fullname not in TRIGGERS:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                break
        else:
            return None
        loader = spec.loader
        if loader is None or not hasattr(loader, "exec_module"):
            return spec
        exec_module = loader.exec_module

        def exec_and_extend(module: ModuleType) -> None:
            exec_module(module)
            from sb3_cql.zoo.plugin import extend

            extend(module)

        loader.exec_module = exec_and_extend  # type: ignore[method-assign]
        return spec


def install() -> None:
    """Add the hook once; zoo modules imported before it are extended now."""
    if not any(isinstance(finder, ZooImportHook) for finder in sys.meta_path):
        sys.meta_path.insert(0, ZooImportHook())
    loaded = [sys.modules[name] for name in TRIGGERS if name in sys.modules]
    if loaded:
        from sb3_cql.zoo.plugin import extend

        for module in loaded:
            extend(module)


install()
