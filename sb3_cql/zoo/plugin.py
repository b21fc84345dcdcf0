"""The zoo plugin: :func:`extend` adds our part to each zoo module in ``hook.TRIGGERS`` right after it is imported
(:mod:`sb3_cql.zoo.hook`); ``import sb3_cql.zoo.plugin`` extends whichever of them are already loaded and installs
the hook for the others. What it registers is in :mod:`sb3_cql.zoo.registry`; what the zoo's ``ExperimentManager``
lacks, in :mod:`sb3_cql.zoo.manager` and the modules named for each behaviour.
"""

from __future__ import annotations

from types import ModuleType

# This module was the plugin's only one: the names it had stay importable from it.
from sb3_cql.zoo.chunked import CHUNKED_KEY  # noqa: F401
from sb3_cql.zoo.errors import INPUT_ERRORS, PROG, SCHEDULE_KEYS, ZOO_KEYS, zoo_parse_error  # noqa: F401
from sb3_cql.zoo.eval_freq import (  # noqa: F401
    CONFIG_OPTIONS,
    ZOO_DEFAULT_EVAL_EPISODES,
    ZOO_DEFAULT_EVAL_FREQ,
    ZOO_DEFAULT_SAVE_FREQ,  # noqa: F401
)
from sb3_cql.zoo.internals import ZOO_INTERNALS, ZooInternal, zoo_internal  # noqa: F401
from sb3_cql.zoo.noise import PINK_SEQ_LEN  # noqa: F401
from sb3_cql.zoo.registry import ALGO, ALGOS, config_file, hyperparams_dir, register_algorithms, register_search_spaces  # noqa: F401


def _extend_utils(utils: ModuleType) -> None:
    from sb3_cql.zoo.checkpoints import checked_model_path  # (SB3 and torch: loaded with the zoo, not with this module)

    register_algorithms(utils)
    if not getattr(utils.get_model_path, "_sb3_cql_wrapped", False):  # enjoy.py and record_video.py import it after
        utils.get_model_path = checked_model_path(utils.get_model_path)


def _extend_exp_manager(exp_manager: ModuleType) -> None:
    from sb3_cql.zoo.manager import extend_exp_manager  # (SB3 and torch, as above)

    extend_exp_manager(exp_manager)


_EXTENSIONS = {
    "rl_zoo3.utils": _extend_utils,
    "rl_zoo3.hyperparams_opt": register_search_spaces,
    "rl_zoo3.exp_manager": _extend_exp_manager,
}


def extend(module: ModuleType) -> None:
    """Add our part to the zoo module ``module`` (once; other modules are left alone)."""
    extension = _EXTENSIONS.get(module.__name__)
    if extension is not None and not getattr(module, "_sb3_cql_extended", False):
        extension(module)
        module._sb3_cql_extended = True  # type: ignore[attr-defined]


# ``import sb3_cql.zoo.plugin`` by hand (e.g. where the .pth file is not processed) extends the zoo modules already
# imported and hooks the others.
from sb3_cql.zoo import hook  # noqa: E402

hook.install()
