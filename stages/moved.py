"""The module paths of the house before its rooms (issue #47), kept importable: ``from pipeline.spike_store import
open_spike_store`` still works, and gives the very module ``pipeline.stores.spike_store`` is (one home), with a
``DeprecationWarning`` naming the new path. Each package lists its own moves in its ``__init__``; this is the
import machinery they share, not an array function."""

import importlib
import importlib.abc
import importlib.util
import sys
import warnings


class _Moved(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds an old module name (after every ordinary finder has not) and loads it as the module it moved to."""

    def __init__(self, moves: dict[str, str]):
        self.moves = moves
        self.specs = {}  # new name -> the module's own spec, which importing it by its old name overwrites

    def find_spec(self, name, path=None, target=None):
        return importlib.util.spec_from_loader(name, self) if name in self.moves else None

    def create_module(self, spec):
        warnings.warn(f"{spec.name} moved to {self.moves[spec.name]}: import it from there", DeprecationWarning,
                      stacklevel=2)
        module = importlib.import_module(self.moves[spec.name])
        self.specs[module.__name__] = module.__spec__
        return module

    def exec_module(self, module):
        module.__spec__ = self.specs[module.__name__]  # its own again (module_from_spec set the old name's)


def keep_importable(package: str, moves: dict[str, str]) -> None:
    """Let ``package.OLD`` import as ``package.NEW`` for each ``OLD: NEW`` of ``moves`` (once per package)."""
    if not any(isinstance(finder, _Moved) and finder.moves.keys() & moves.keys() for finder in sys.meta_path):
        sys.meta_path.append(_Moved({f"{package}.{old}": f"{package}.{new}" for old, new in moves.items()}))
