"""Import :mod:`sb3_cql.zoo.plugin` right after the package ``rl_zoo3`` is, in any process. ``sb3_cql-zoo.pth``
imports this module at start-up: it imports ``sys`` only (a plain class with ``find_spec`` is a meta path finder)."""

import sys


class ZooImportHook:
    """A meta path finder that finds nothing itself: it wraps the loader of ``rl_zoo3`` that another finder gives."""

    def find_spec(self, fullname, path=None, target=None):  # -> ModuleSpec | None (typing is not imported)
        if fullname != "rl_zoo3":
            return None
        finders = [finder for finder in sys.meta_path if finder is not self and hasattr(finder, "find_spec")]
        spec = next(filter(None, (finder.find_spec(fullname, path, target) for finder in finders)), None)
        if spec is None or not hasattr(spec.loader, "exec_module"):
            return spec
        exec_module = spec.loader.exec_module

        def exec_and_register(module) -> None:
            exec_module(module)
            __import__("sb3_cql.zoo.plugin")  # registers on import

        spec.loader.exec_module = exec_and_register
        return spec


if not any(type(finder).__name__ == ZooImportHook.__name__ for finder in sys.meta_path):
    sys.meta_path.insert(0, ZooImportHook())
