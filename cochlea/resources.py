"""Files that ship with the package: robot descriptions, scenarios, code-generation templates.

In the repository they are at the top level, as the design lays it out: ``models/robots/*.toml``
(the descriptions), ``models/scenarios/*.toml`` (the thesis's simulation studies),
``models/examples/`` (example user robots and their starter scenarios) and ``codegen/`` (what
``cochlea-codegen`` generates, and the closed-loop driver's template). A wheel carries the same
two folders inside the package, as ``cochlea/data/models/`` and ``cochlea/data/codegen/``
(``setup.py`` copies them there at build time). :func:`data_root` says which of the two a run
uses, so a checkout (or an editable install) and an installed wheel find them alike.

The checkout itself (``checkout()``) holds what is not shipped: ``generated_c/`` and the
``build/`` folder with ``libcochlea.so``.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

from .errors import CochleaError


def checkout() -> Path | None:
    """The repository the package runs from (an editable install), or None when installed:
    the folder above the package, if it holds ``generated_c/``."""
    root = Path(__file__).resolve().parent.parent
    return root if (root / "generated_c").is_dir() else None


def data_root() -> Path:
    """The folder that holds ``models/`` and ``codegen/``: the checkout's top level when run from
    one, else the installed package's ``data/`` folder (where the wheel carries them)."""
    root = checkout()
    return root if root is not None else Path(str(resources.files("cochlea") / "data"))


DATA = data_root()
MODELS_DIR = DATA / "models"
ROBOTS_DIR = MODELS_DIR / "robots"
SCENARIOS_DIR = MODELS_DIR / "scenarios"
#: Example user robots (descriptions in the shipped format) and their starter scenarios.
EXAMPLES_DIR = MODELS_DIR / "examples"
CODEGEN_DIR = DATA / "codegen"
#: Where a wheel carries the compiled C kernels (``setup.py`` builds them from generated_c/).
PACKAGED_LIBRARY = Path(str(resources.files("cochlea") / "lib" / "libcochlea.so"))


class AmbiguousName(CochleaError):
    """A bare name that is both a shipped file's and a local file's or folder's."""


def shipped_file(folder: Path, name: str) -> Path:
    """The shipped file a bare ``name`` stands for in ``folder`` (``ROBOTS_DIR``,
    ``SCENARIOS_DIR``): ``<folder>/<name>.toml``. A default the user did not type is passed as
    this path, so that :func:`shipped`'s refusal of an ambiguous bare name never meets it."""
    return folder / f"{name}.toml"


def shipped(folder: Path, name_or_path: str | Path) -> Path:
    """A bare name such as ``"serial"`` means ``<folder>/serial.toml``; anything else (a name
    with a ``.toml`` suffix or a folder part, ``./serial`` included) is a path of the user's.

    A bare name that is also a file or folder in the working directory is refused
    (:class:`AmbiguousName`, whose text says how to name either): loading the shipped robot
    when ``./serial`` is the user's own description would run the wrong robot silently.
    (A default, which the user did not type, is passed as the shipped file's path.)"""
    text = str(name_or_path)
    candidate = Path(name_or_path)
    if (isinstance(name_or_path, str) and text.startswith(("./", ".\\"))) or not text:
        return candidate
    if candidate.suffix != ".toml" and candidate.parent == Path("."):
        if os.path.lexists(candidate):
            mine = (f"the {'folder' if os.path.isdir(candidate) else 'file'} "
                    f"{os.path.abspath(text)} here")
            ship = shipped_file(folder, text)
            raise AmbiguousName(
                (f"{text!r} names both the shipped {ship} and {mine}" if ship.is_file() else
                 f"{text!r}, a bare name, means the shipped {ship} (there is none), not {mine}")
                + f": give {os.path.join('.', text)} or its full path for yours"
                + (", or run from another folder for the shipped one" if ship.is_file()
                   else ""))
        return shipped_file(folder, text)
    return candidate
