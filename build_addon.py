"""Build the installable Blender add-on zips into dist/.

    python build_addon.py [--out dist]

Writes two zips holding the same add-on (package `diffsheg`: blender_addon/ with the
presets and diffsheg_core, weights included, under lib/):
- diffsheg-<version>.zip: a Blender 4.2+ extension (blender_manifest.toml at the root),
  for Edit > Preferences > Get Extensions > Install from Disk;
- diffsheg-<version>-legacy.zip: a legacy add-on (folder diffsheg/ with bl_info), for
  Edit > Preferences > Add-ons > Install on older versions.
torch, librosa and soundfile are not bundled: the add-on's preferences install them.
"""

from __future__ import annotations

import argparse
import re
import sys
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parent
PACKAGE = "diffsheg"
SKIP_DIRS = {"__pycache__", ".pytest_cache"}
SKIP_SUFFIXES = {".pyc", ".pyo"}


def version() -> str:
    text = (REPO / "blender_addon" / "blender_manifest.toml").read_text(encoding="utf-8")
    return re.search(r'^version\s*=\s*"([^"]+)"', text, re.MULTILINE).group(1)


def _files(root: Path):
    for path in sorted(root.rglob("*")):
        if path.is_file() and not SKIP_DIRS & set(path.relative_to(root).parts) \
                and path.suffix not in SKIP_SUFFIXES:
            yield path


def addon_entries() -> list[tuple[Path, str]]:
    """(source file, path inside the add-on folder) for everything the add-on needs."""
    entries = [(p, p.relative_to(REPO / "blender_addon").as_posix()) for p in _files(REPO / "blender_addon")]
    entries += [(p, f"presets/{p.name}") for p in sorted((REPO / "presets").glob("*.json"))]
    entries += [(p, f"lib/{p.relative_to(REPO).as_posix()}") for p in _files(REPO / "diffsheg_core")]
    for license_name in ("LICENSE", "LICENSE.txt"):
        if (REPO / license_name).is_file():
            entries.append((REPO / license_name, license_name))
    return entries


def write_zip(path: Path, entries: list[tuple[Path, str]], prefix: str, skip: set[str]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for source, name in entries:
            if name not in skip:
                zf.write(source, prefix + name)
    return path


def build(out: Path) -> tuple[Path, Path]:
    entries = addon_entries()
    v = version()
    extension = write_zip(out / f"{PACKAGE}-{v}.zip", entries, "", set())
    legacy = write_zip(out / f"{PACKAGE}-{v}-legacy.zip", entries, f"{PACKAGE}/", {"blender_manifest.toml"})
    return extension, legacy


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(REPO / "dist"), help="output folder (default dist/)")
    args = parser.parse_args(argv)
    for path in build(Path(args.out)):
        print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
