"""Build the installable Blender add-on zips into dist/.

    python build_addon.py [--out dist] [--platform linux-x64 ...] [--no-legacy] [--wheel-cache DIR]

Writes the add-on (package `diffsheg`: blender_addon/ with its ui/, features/ and scene/,
the presets, batch_render.py and studio.py beside it, and the runtime of diffsheg_core with
the bundled model under lib/):
- diffsheg-<version>-<platform>.zip for each Blender platform (windows-x64, macos-arm64,
  macos-x64, linux-x64; --platform picks some): a Blender 4.2+ extension that bundles the
  runtime's Python packages as wheels (wheels/, listed with `platforms` and `wheels` in
  the zip's blender_manifest.toml), which Blender installs from the zip, offline. Install
  it with Edit > Preferences > Get Extensions > Install from Disk;
- diffsheg-<version>-legacy.zip: a legacy add-on (folder diffsheg/ with bl_info, no
  wheels) for Blender before 4.2 (Edit > Preferences > Add-ons > Install); its
  preferences install the runtime packages with pip.

The wheels are downloaded from PyPI once, with pip, into a cache folder
($DIFFSHEG_WHEEL_CACHE, default ~/.cache/diffsheg/wheels; --wheel-cache), at the versions
pinned in WHEELS below, for CPython 3.11 (Blender 4.2-5.0). Each zip records the pins
and every wheel's file name, size and sha256 in wheels/wheels.json. The tooling
(diffsheg_core/training/, diffsheg_core/torch_layer/export.py) stays out of every zip. The
add-on runs without torch; the rest of diffsheg_core/torch_layer/ ships for when its user
installs torch (GPU support: official checkpoints, CUDA GPUs).
blender_addon/blender_manifest.toml is the template of the manifest.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parent
PACKAGE = "diffsheg"
PYTHON_VERSION = "3.11"  # the Python of Blender 4.2 to 5.0; the wheels are built for it

# The runtime's wheels: distribution -> version. Only what `diffsheg_core.generate` imports
# on the onnx path, and what those packages need at run time that Blender lacks (it ships
# numpy). onnxruntime declares flatbuffers, packaging, protobuf (and sympy as an extra):
# building and running an InferenceSession from bytes needs none of them, so they are left
# out. soundfile needs cffi's compiled `_cffi_backend` (not pycparser: its binding is
# pre-built) and imports typing_extensions.
WHEELS: dict[str, str] = {
    "onnxruntime": "1.32.0",
    "soundfile": "0.14.0",
    "cffi": "2.1.1",
    "typing-extensions": "4.16.0",
    "soxr": "1.1.0",
    "safetensors": "0.8.0",
    # numpy's BLAS held to the generation's threads (runtime.backends.cpu_threads; pure Python)
    "threadpoolctl": "3.8.0",
    # live generation (diffsheg_core.live): the microphone (sounddevice: its Windows and macOS
    # wheels carry PortAudio, Linux needs the system's libportaudio2; it uses cffi, above) and
    # the VMC protocol over OSC (python-osc, pure Python)
    "sounddevice": "0.5.6",
    "python-osc": "1.10.2",
}
# Where a platform has no wheel of the version above.
PLATFORM_PINS: dict[str, dict[str, str]] = {
    "macos-x64": {"onnxruntime": "1.23.2"},  # the last onnxruntime with Intel macOS wheels
}
PURE_PYTHON = {"typing-extensions", "python-osc", "threadpoolctl"}  # one py3-none-any wheel serves every platform

# Blender platform -> pip --platform tags, the preferred (oldest OS) first. Blender itself
# runs on glibc 2.28+ and macOS 11.2+; a wheel may ask for a newer OS (wheels.json says).
PLATFORMS: dict[str, tuple[str, ...]] = {
    "windows-x64": ("win_amd64",),
    "macos-arm64": ("macosx_11_0_arm64", "macosx_15_0_arm64"),
    "macos-x64": ("macosx_11_0_x86_64", "macosx_15_0_x86_64"),
    "linux-x64": ("manylinux2014_x86_64",) + tuple(f"manylinux_2_{m}_x86_64" for m in range(17, 29)),
}
WHEEL_CACHE_ENV = "DIFFSHEG_WHEEL_CACHE"

SKIP_DIRS = {"__pycache__", ".pytest_cache"}
SKIP_SUFFIXES = {".pyc", ".pyo"}
CORE_EXCLUDE = ("training/", "torch_layer/export.py")  # tooling, relative to diffsheg_core/


class BuildError(Exception):
    """A build step failed; the message says which and why."""


def version() -> str:
    text = (REPO / "blender_addon" / "blender_manifest.toml").read_text(encoding="utf-8")
    return re.search(r'^version\s*=\s*"([^"]+)"', text, re.MULTILINE).group(1)


def pins(platform: str) -> dict[str, str]:
    """The wheel versions of one platform."""
    return {**WHEELS, **PLATFORM_PINS.get(platform, {})}


def default_cache() -> Path:
    env = os.environ.get(WHEEL_CACHE_ENV)
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "diffsheg" / "wheels"


# ---------------------------------------------------------------- wheels

def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "_", name).lower()


def _cached_wheel(folder: Path, name: str, wanted: str) -> Path | None:
    if not folder.is_dir():
        return None
    prefix = f"{_normalise(name)}-{wanted}-"
    found = sorted(p for p in folder.glob("*.whl") if p.name.lower().startswith(prefix.lower()))
    return found[0] if found else None


def fetch_wheel(name: str, wanted: str, platform: str, cache: Path) -> Path:
    """The wheel of `name`==`wanted` for `platform` (CPython 3.11), from the cache or, the
    first time, downloaded from PyPI with pip into it."""
    pure = name in PURE_PYTHON
    folder = cache / ("any" if pure else platform)
    cached = _cached_wheel(folder, name, wanted)
    if cached is not None:
        return cached
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        command = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
                   "--disable-pip-version-check", "--no-input", "--python-version", PYTHON_VERSION,
                   "--dest", tmp]
        if not pure:
            for tag in PLATFORMS[platform]:
                command += ["--platform", tag]
        command.append(f"{name}=={wanted}")
        print(f"downloading {name}=={wanted} for {'any platform' if pure else platform}", flush=True)
        proc = subprocess.run(command, capture_output=True, text=True)
        wheels = sorted(Path(tmp).glob("*.whl"))
        if proc.returncode != 0 or len(wheels) != 1:
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
            raise BuildError(f"pip could not download {name}=={wanted} for {platform} "
                             f"(Python {PYTHON_VERSION}): {' | '.join(tail) or 'no wheel'}")
        target = folder / wheels[0].name
        os.replace(wheels[0], target)
    return target


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def platform_wheels(platform: str, cache: Path) -> list[Path]:
    return [fetch_wheel(name, wanted, platform, cache) for name, wanted in pins(platform).items()]


def _required_os(wheels: list[Path]) -> str | None:
    """The newest OS release any of the wheels asks for (macOS version, glibc), if any."""
    mac, glibc = (0, 0), (0, 0)
    for wheel in wheels:
        tags = wheel.stem.split("-")[-1].split(".")
        macs = [tuple(map(int, m.groups())) for t in tags if (m := re.match(r"macosx_(\d+)_(\d+)_", t))]
        libcs = [tuple(map(int, m.groups())) for t in tags if (m := re.match(r"manylinux_(\d+)_(\d+)_", t))]
        libcs += [(2, 17) for t in tags if t.startswith("manylinux2014")]
        if macs:
            mac = max(mac, min(macs))
        if libcs:
            glibc = max(glibc, min(libcs))
    if mac > (0, 0):
        return f"macOS {mac[0]}.{mac[1]}"
    if glibc > (0, 0):
        return f"glibc {glibc[0]}.{glibc[1]}"
    return None


def wheels_record(platform: str, wheels: list[Path]) -> dict:
    return {
        "platform": platform,
        "python": PYTHON_VERSION,
        "pins": pins(platform),
        "requires_os": _required_os(wheels),
        "wheels": [{"file": w.name, "size": w.stat().st_size, "sha256": sha256(w)} for w in wheels],
    }


# ---------------------------------------------------------------- zips

def _files(root: Path):
    for path in sorted(root.rglob("*")):
        if path.is_file() and not SKIP_DIRS & set(path.relative_to(root).parts) \
                and path.suffix not in SKIP_SUFFIXES:
            yield path


def _core_files():
    root = REPO / "diffsheg_core"
    for path in _files(root):
        rel = path.relative_to(root).as_posix()
        if not any(rel == e or (e.endswith("/") and rel.startswith(e)) for e in CORE_EXCLUDE):
            yield path


def addon_entries() -> list[tuple[Path, str]]:
    """(source file, path inside the add-on folder) for everything the add-on needs."""
    entries = [(p, p.relative_to(REPO / "blender_addon").as_posix()) for p in _files(REPO / "blender_addon")]
    entries += [(REPO / name, name) for name in ("batch_render.py", "studio.py")]  # the headless drivers
    entries += [(p, f"presets/{p.name}") for p in sorted((REPO / "presets").glob("*.json"))]
    entries += [(p, f"lib/{p.relative_to(REPO).as_posix()}") for p in _core_files()]
    for license_name in ("LICENSE", "LICENSE.txt"):
        if (REPO / license_name).is_file():
            entries.append((REPO / license_name, license_name))
    return entries


def extension_manifest(platform: str, wheel_names: list[str]) -> str:
    """The template manifest with this zip's `platforms` and `wheels` (top-level keys,
    so they go before the first table)."""
    text = (REPO / "blender_addon" / "blender_manifest.toml").read_text(encoding="utf-8")
    text = re.sub(r"^(platforms|wheels)\s*=.*?\]\s*$", "", text, flags=re.MULTILINE | re.DOTALL)
    lines = [f'platforms = ["{platform}"]', "wheels = ["]
    lines += [f'  "./wheels/{name}",' for name in wheel_names]
    lines += ["]", ""]
    table = re.search(r"^\[", text, re.MULTILINE)
    at = table.start() if table else len(text)
    return text[:at] + "\n".join(lines) + "\n" + text[at:]


def _write_zip(path: Path, files: list[tuple[Path, str]], texts: dict[str, str]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".part")
    with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED, compresslevel=6) as zf:
        for name, text in texts.items():
            zf.writestr(name, text)
        for source, name in files:
            stored = source.suffix == ".whl"  # already compressed
            zf.write(source, name, compress_type=zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED)
    os.replace(partial, path)
    return path


def build_extension(out: Path, platform: str, cache: Path) -> Path:
    if platform not in PLATFORMS:
        raise BuildError(f"unknown platform '{platform}': use {', '.join(PLATFORMS)}")
    wheels = platform_wheels(platform, cache)
    files = [(s, n) for s, n in addon_entries() if n != "blender_manifest.toml"]
    files += [(w, f"wheels/{w.name}") for w in wheels]
    record = wheels_record(platform, wheels)
    texts = {
        "blender_manifest.toml": extension_manifest(platform, [w.name for w in wheels]),
        "wheels/wheels.json": json.dumps(record, indent=2) + "\n",
    }
    return _write_zip(out / f"{PACKAGE}-{version()}-{platform}.zip", files, texts)


def build_legacy(out: Path) -> Path:
    files = [(s, f"{PACKAGE}/{n}") for s, n in addon_entries() if n != "blender_manifest.toml"]
    return _write_zip(out / f"{PACKAGE}-{version()}-legacy.zip", files, {})


def build(out: Path, platforms: list[str] | None = None, legacy: bool = True,
          cache: Path | None = None) -> dict[str, Path]:
    """Build the zips; returns {platform or 'legacy': zip path}."""
    cache = cache or default_cache()
    chosen = list(PLATFORMS) if platforms is None else platforms
    built = {p: build_extension(out, p, cache) for p in chosen}
    if legacy:
        built["legacy"] = build_legacy(out)
    return built


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(REPO / "dist"), help="output folder (default dist/)")
    parser.add_argument("--platform", action="append", choices=list(PLATFORMS),
                        help="build this platform's extension (repeatable; default all)")
    parser.add_argument("--no-legacy", action="store_true", help="skip the legacy (pre-4.2) zip")
    parser.add_argument("--wheel-cache", default=None,
                        help=f"wheel download cache (default ${WHEEL_CACHE_ENV} or ~/.cache/diffsheg/wheels)")
    args = parser.parse_args(argv)
    try:
        built = build(Path(args.out), args.platform, legacy=not args.no_legacy,
                      cache=Path(args.wheel_cache).expanduser() if args.wheel_cache else None)
    except BuildError as exc:
        print(f"build_addon: error: {exc}", file=sys.stderr)
        return 1
    for path in built.values():
        print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
