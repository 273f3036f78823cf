"""Not a module: the root folder of a flowrt clone (a source checkout).

Python reads this file only when ``import flowrt`` runs in the folder that *holds* the clone
(its current directory comes first on ``sys.path``). Without it the clone's folder became an
empty namespace package, even where flowrt is installed, and ``flowrt.Runtime`` failed far
from the cause. Here the installed flowrt is loaded in its place when there is one (a wheel,
``pip install -e``); else the import stops with what to do.
"""

if __name__ == "flowrt":
    import importlib.machinery as _machinery
    import importlib.util as _util
    import os as _os
    import sys as _sys

    def _installed() -> _machinery.ModuleSpec | None:
        here = _os.path.abspath(__file__)
        holder = _os.path.dirname(_os.path.dirname(here))
        path = [p for p in _sys.path if _os.path.abspath(p or _os.curdir) != holder]
        for finder in _sys.meta_path:
            if finder is _machinery.PathFinder:
                spec = finder.find_spec("flowrt", path)
            else:
                find = getattr(finder, "find_spec", None)
                spec = find("flowrt", None) if find is not None else None
            if spec is not None and spec.loader is not None and spec.origin != here:
                return spec
        return None

    _spec = _installed()
    if _spec is None or _spec.loader is None:
        raise ImportError(
            f"'import flowrt' found {_os.path.dirname(_os.path.abspath(__file__))}, a flowrt "
            "source checkout, and flowrt is not installed in this Python "
            f"({_sys.executable}): install it (python3 -m venv .venv && . .venv/bin/activate "
            "&& pip install -e ./flowrt), or use the Python where it is installed",
            name="flowrt",
        )
    _module = _util.module_from_spec(_spec)
    _sys.modules["flowrt"] = _module  # what `import flowrt` returns: the installed package
    _spec.loader.exec_module(_module)
