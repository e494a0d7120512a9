"""A user's class named by import path ("package.module:Class"), as settings name one (``[model] class``,
``[federation] strategy``)."""

from __future__ import annotations

import importlib
import importlib.util

from crchfl_sumo.core.errors import CrchflError

FIX = "install the package or put its folder on PYTHONPATH"


def import_class(path: str, key: str) -> type:
    """The class ``path`` names, its module imported (its code runs); a one-line CrchflError naming the
    setting ``key`` and the fix where the path is malformed, its module missing or failing, or no class."""
    module_name, _, class_name = path.partition(":")
    if not module_name or not class_name:
        raise CrchflError(f"{key}: {path!r} is no import path; give \"package.module:Class\"")
    try:
        found = importlib.util.find_spec(module_name)
    except (ImportError, ValueError):  # a parent package that is missing, or a malformed name
        found = None
    if found is None:
        raise CrchflError(f"{key}: module {module_name!r} of {path!r} is not importable here; {FIX}")
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # the user's module: anything may go wrong in it, and it is reported in one line
        raise CrchflError(f"{key}: importing {module_name!r} failed ({type(exc).__name__}: {exc})") from None
    cls = getattr(module, class_name, None)
    if not isinstance(cls, type):
        raise CrchflError(f"{key}: {path!r} names no class in {module_name!r}; name one")
    return cls
