"""Files that ship inside the package: robot descriptions, scenarios, code-generation templates.

They are found through :mod:`importlib.resources`, so an installed wheel finds them as well as a
checkout does: ``data/robots/*.toml`` (the descriptions), ``data/scenarios/*.toml`` (the thesis's
simulation studies) and ``data/codegen/`` (what ``cochlea-codegen`` generates, and the
closed-loop driver's template).

The checkout itself (``checkout()``) holds what is not shipped: ``generated_c/`` and the
``build/`` folder with ``libcochlea.so``.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

#: Folder of the package's data files.
DATA = Path(str(resources.files("cochlea") / "data"))
ROBOTS_DIR = DATA / "robots"
SCENARIOS_DIR = DATA / "scenarios"
CODEGEN_DIR = DATA / "codegen"
#: Where a wheel carries the compiled C kernels (``setup.py`` builds them from generated_c/).
PACKAGED_LIBRARY = Path(str(resources.files("cochlea") / "lib" / "libcochlea.so"))


def shipped(folder: Path, name_or_path: str | Path) -> Path:
    """A bare name such as ``"serial"`` means ``<folder>/serial.toml``; anything else (a name
    with a ``.toml`` suffix or a folder part) is a path of the user's."""
    candidate = Path(name_or_path)
    if candidate.suffix != ".toml" and candidate.parent == Path("."):
        return folder / f"{candidate}.toml"
    return candidate


def checkout() -> Path | None:
    """The repository the package runs from (an editable install), or None when installed:
    the folder above the package, if it holds ``generated_c/``."""
    root = Path(__file__).resolve().parent.parent
    return root if (root / "generated_c").is_dir() else None
