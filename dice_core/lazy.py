"""Libraries imported on their first use, so that a step's process does not pay for the ones it never reaches.

A workflow step is a fresh process; importing xarray (with pandas) costs about 0.3 s of it on an idle core,
more than everything else before the step's first log line (BENCHMARKS.md, "A step's fixed cost"). Modules
that use such a library throughout bind it with :func:`module` instead of ``import``; libraries a module uses
in one or two functions are imported in those functions instead.

On Python 3.11 the standard library's lazy loader is not thread-safe: two threads that first touch a deferred
package at the same moment can see it half-imported (CPython issue gh-114763, fixed in 3.13 and a 3.12 bugfix
release). The pipeline's steps run one thread of Python (their workers are processes); a program that calls
:mod:`dice_core` from threads should import ``xarray`` (and ``jsonschema``) itself before it starts them.
"""

from __future__ import annotations

import importlib.util
import sys

__all__ = ["module"]


def module(name: str):
    """The top-level package ``name``, imported when one of its attributes is first used (the standard
    library's :class:`importlib.util.LazyLoader`); the package itself if it is already imported.

    Raises
    ------
    ModuleNotFoundError
        ``name`` is not installed (found at once, not at first use).
    """
    if "." in name:  # finding a submodule imports its parents: nothing would be deferred
        raise ValueError(f"{name}: a top-level package only")
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    if spec is None:
        raise ModuleNotFoundError(f"No module named {name!r}", name=name)
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    lazy = importlib.util.module_from_spec(spec)
    sys.modules[name] = lazy
    loader.exec_module(lazy)
    return lazy
