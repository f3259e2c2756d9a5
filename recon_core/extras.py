"""Optional extras: what each needs beyond the default install, found without importing it.

A name here is both a choice in the configuration and the extra that brings its packages
(`pip install 'aerec[NAME]'`, pyproject.toml's optional-dependencies)."""

from __future__ import annotations

import importlib.util

# import names of the packages an extra brings
EXTRAS = {"pandora": ("pandora", "pandora_plugin_libsgm")}


def missing_packages(name: str) -> list[str]:
    """The packages extra `name` needs that this Python cannot import (found, not imported)."""
    def absent(module: str) -> bool:
        try:
            return importlib.util.find_spec(module) is None
        except (ImportError, ValueError):
            return True

    return [m for m in EXTRAS.get(name, ()) if absent(m)]
