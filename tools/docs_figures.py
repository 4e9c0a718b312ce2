"""Make the pictures of the README and the docs site (docs/images/), from the repository.

    python tools/docs_figures.py plots     # benchmark plots from tools/docs_figures_data.json (matplotlib)
    python tools/docs_figures.py demo      # a still of the main job's preview (out/demo.mp4; ffmpeg)
    python tools/docs_figures.py feet      # the capture's feet beside the generated (bench/render_feet.py)
    python tools/docs_figures.py panel     # the sidebar panel in a real Blender window (Xvfb)
    python tools/docs_figures.py all

plots: the figures already measured and published (keys against Blender's Decimate, live
latency, the two backends), each captioned with its bench, machine and date. The numbers
live in tools/docs_figures_data.json: change one only with a new measurement.

demo: runs the main job (`python batch_render.py`) when out/demo.mp4 is missing (or with
--render), then puts a frame of the whole body and one of the face close-up side by side.

panel: builds the legacy add-on zip (build_addon.build_legacy), installs the runtime wheels
of the linux-x64 extension (build_addon.platform_wheels: cached, or fetched from PyPI once)
into a throw-away Blender home so the panel shows no "missing packages" box, and runs
tools/panel_screenshot.py twice under xvfb-run: the panel as it opens, and with its
sub-panels open. Needs a Blender 3.4+ and Xvfb (`bash tools/install_system_packages.sh
--screenshots` installs Debian's Blender 3.4 with numpy, and Xvfb). The crops are set for that Blender at the screen
sizes below; check the pictures after a change of Blender or of the panel.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "tools" / "docs_figures_data.json"
IMAGES = REPO / "docs" / "images"


def _save(fig, group: dict, out: Path, bottom: float) -> Path:
    """Caption the figure with where and when its numbers were measured, and write it."""
    import matplotlib.pyplot as plt

    fig.text(0.01, 0.012, f"Measured {group['date']} on a {group['machine']}: {group['bench']}",
             fontsize=8, color="#444444", ha="left", va="bottom")
    fig.subplots_adjust(bottom=bottom, top=0.92)
    fig.savefig(out)
    plt.close(fig)
    return out


def plot_keys(data: dict, out: Path) -> Path:
    import matplotlib.pyplot as plt

    g = data["keys"]
    kinds = (("bone", "per bone"), ("shape_key", "per shape key"))
    methods = [f"Every frame ({g['scene_fps']} fps)", *g["ours_over"], "Ours (sparse Bezier poses)"]
    values = {m: [] for m in methods}
    for kind, _ in kinds:
        ours = g["ours"][kind]
        values[methods[0]].append(float(g["scene_fps"]))
        for other, ratio in g["ours_over"].items():
            values[other].append(ours / ratio[kind])  # the bench printed ours / theirs
        values[methods[-1]].append(ours)
    colors = ("#bbbbbb", "#8c9fca", "#e78ac3", "#1b9e77")
    fig, ax = plt.subplots(figsize=(8, 4.2), dpi=110)
    width = 0.2
    for i, (method, color) in enumerate(zip(methods, colors)):
        xs = [k + (i - 1.5) * width for k in range(len(kinds))]
        bars = ax.bar(xs, values[method], width, label=method, color=color)
        ax.bar_label(bars, fmt="%.2f", fontsize=8, padding=2)
    ax.set_xticks(range(len(kinds)), [f"keys per second {label}" for _, label in kinds])
    ax.set_ylabel("keys per second (fewer is easier to edit)")
    ax.set_yscale("log")
    ax.set_ylim(1, 60)
    ax.set_yticks([1, 2, 5, 10, 20, 50], ["1", "2", "5", "10", "20", "50"])
    ax.minorticks_off()
    ax.set_title(g["title"], fontsize=10)
    ax.legend(fontsize=8, loc="upper right", ncols=2)
    ratios = "; ".join(f"{name.split(' (')[0]} {r['bone']:.2f}x per bone, {r['shape_key']:.2f}x per shape key"
                       for name, r in g["ours_over"].items())
    fig.text(0.01, 0.048, textwrap.fill(f"Ours over theirs at the same measured worst error, as the bench "
                                        f"printed it: {ratios}.", 140), fontsize=8, color="#444444", va="bottom")
    return _save(fig, g, out, 0.2)


def plot_live(data: dict, out: Path) -> Path:
    import matplotlib.pyplot as plt

    g = data["live_latency"]
    fig, ax = plt.subplots(figsize=(8, 4.2), dpi=110)
    stats = ("p50", "p95", "max")
    groups = [(row["setting"], load, row[load]) for row in g["rows"] for load in ("idle", "busy")]
    width = 0.25
    colors = ("#66c2a5", "#fc8d62", "#8da0cb")
    for i, (stat, color) in enumerate(zip(stats, colors)):
        xs = [k + (i - 1) * width for k in range(len(groups))]
        bars = ax.bar(xs, [values[stat] for _, _, values in groups], width, label=stat, color=color)
        ax.bar_label(bars, fmt="%.2f", fontsize=8, padding=2)
    ax.axhline(g["goal_p95_s"], color="#d62728", linestyle="--", linewidth=1,
               label=f"goal: p95 under {g['goal_p95_s']} s")
    labels = [f"{setting}\n{'idle' if load == 'idle' else 'one core kept busy'}" for setting, load, _ in groups]
    ax.set_xticks(range(len(groups)), labels, fontsize=8)
    ax.set_ylabel("latency (s)")
    ax.set_ylim(0, 0.75)
    ax.set_title(g["title"], fontsize=10)
    ax.legend(fontsize=8, loc="upper left", ncols=4)
    compute = ", ".join(f"{row['setting']}: {row['compute_per_s']:.2f} s" for row in g["rows"])
    fig.text(0.01, 0.055, f"Compute per second of speech: {compute}.", fontsize=8, color="#444444")
    return _save(fig, g, out, 0.21)


def plot_backends(data: dict, out: Path) -> Path:
    import matplotlib.pyplot as plt

    g = data["backends"]
    fig, ax = plt.subplots(figsize=(8, 4.2), dpi=110)
    rows = g["rows"]
    width = 0.36
    labels = [f"{row['backend']}, {row['threads']} thread{'s' if row['threads'] > 1 else ''}" for row in rows]
    for i, (key, label, color) in enumerate((("idle_s", "idle", "#66c2a5"),
                                             ("busy_s", "one core kept busy", "#fc8d62"))):
        xs = [k + (i - 0.5) * width for k in range(len(rows))]
        bars = ax.bar(xs, [row[key] for row in rows], width, label=label, color=color)
        ax.bar_label(bars, fmt="%.2f s", fontsize=8, padding=2)
    ax.set_xticks(range(len(rows)), labels)
    ax.set_ylabel("seconds for 60 s of speech")
    ax.set_ylim(0, 26)
    ax.set_title(g["title"], fontsize=10)
    ax.legend(fontsize=8, loc="upper left")
    return _save(fig, g, out, 0.14)


def plots() -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    data = json.loads(DATA.read_text(encoding="utf-8"))
    IMAGES.mkdir(parents=True, exist_ok=True)
    return [plot_keys(data, IMAGES / "bench-keys.png"), plot_live(data, IMAGES / "bench-live-latency.png"),
            plot_backends(data, IMAGES / "bench-backends.png")]


def demo(render: bool = False, body_at: float = 2.5, face_at: float = 5.8) -> list[Path]:
    """A frame of the whole body (the preview's first 4 s) beside one of the face close-up (4-8 s)."""
    video = REPO / "out" / "demo.mp4"
    if render or not video.exists():
        subprocess.run([sys.executable, "batch_render.py"], cwd=REPO, check=True)
    IMAGES.mkdir(parents=True, exist_ok=True)
    out = IMAGES / "demo-still.png"
    with tempfile.TemporaryDirectory() as tmp:
        frames = []
        for name, at in (("body", body_at), ("face", face_at)):
            frame = Path(tmp) / f"{name}.png"
            subprocess.run(["ffmpeg", "-v", "error", "-y", "-ss", str(at), "-i", str(video), "-frames:v", "1",
                            str(frame)], check=True)
            frames.append(frame)
        subprocess.run(["ffmpeg", "-v", "error", "-y", "-i", str(frames[0]), "-i", str(frames[1]),
                        "-filter_complex", "hstack=inputs=2", str(out)], check=True)
    return [out]


def feet(render: bool = False) -> list[Path]:
    """The contact sheet of bench/render_feet.py: the capture and the generated take of the same
    speech side by side, whole body and feet."""
    sheet = REPO / "out" / "render-feet" / "feet_sheet.png"
    if render or not sheet.exists():
        subprocess.run([sys.executable, "bench/render_feet.py", "--seconds", "10", "--out", "out/render-feet"],
                       cwd=REPO, check=True)
    IMAGES.mkdir(parents=True, exist_ok=True)
    out = IMAGES / "feet-sheet.png"
    shutil.copyfile(sheet, out)
    return [out]


# (file, screen, panel_screenshot.py flags, crop as (left, top, bottom) in pixels: left from the
# area's right edge, bottom from its top): set for Debian's Blender 3.4 at these screen sizes
SHOTS = (
    ("panel.png", "1600x1200x24", (), (600, 0, 822)),
    ("panel-open.png", "1600x1900x24", ("--open",), (262, 50, 1640)),
)


def _blender_env(home: Path) -> dict:
    """The environment for a distribution's Blender, which runs on the system's Python: a home
    of its own, and no PATH entry of the Python running this script (a pyenv or a venv put
    first on PATH makes that Blender take their standard library and lose the system's numpy)."""
    ours = {str(Path(p).resolve()) for p in (sys.prefix, sys.base_prefix)}
    keep = [entry for entry in os.environ.get("PATH", "").split(os.pathsep)
            if entry and "pyenv" not in entry and not any(str(Path(entry).resolve()).startswith(p) for p in ours)]
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYENV", "VIRTUAL_ENV", "PYTHONHOME", "PYTHONPATH"))}
    return {**env, "HOME": str(home), "PATH": os.pathsep.join(keep)}


def _run_blender(command: list[str], env: dict, out: Path, timeout: float = 180) -> None:
    """Run a Blender window under Xvfb until it has saved `out`. A script error in Blender's
    GUI leaves the window open instead of failing, so a run that has not saved `out` in
    `timeout` seconds is ended (with Xvfb) and reported."""
    process = subprocess.Popen(command, env=env, start_new_session=True)
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGTERM)
        process.wait(timeout=30)
    if not out.exists():
        raise SystemExit(f"panel: Blender saved no {out.name} within {timeout:g} s: see its output above "
                         f"(tools/panel_screenshot.py)")


def panel(blender: str = "blender") -> list[Path]:
    sys.path.insert(0, str(REPO))
    import build_addon
    from PIL import Image

    blender = shutil.which(blender) or blender
    if not Path(blender).exists() or shutil.which("xvfb-run") is None:
        raise SystemExit("panel: needs Blender 3.4+ and xvfb-run (bash tools/install_system_packages.sh --screenshots)")
    IMAGES.mkdir(parents=True, exist_ok=True)
    made = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        addon_zip = build_addon.build_legacy(tmp / "dist")
        home = tmp / "home"
        version = subprocess.run([blender, "--version"], capture_output=True, text=True, check=True).stdout.split()[1]
        modules = home / ".config" / "blender" / ".".join(version.split(".")[:2]) / "scripts" / "modules"
        wheels = build_addon.platform_wheels("linux-x64", build_addon.default_cache())
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(modules),
                        *map(str, wheels)], check=True)
        env = _blender_env(home)
        for name, screen, flags, (left, top, bottom) in SHOTS:
            raw = tmp / name
            _run_blender(["xvfb-run", "-a", "-s", f"-screen 0 {screen}", blender, "--factory-startup",
                          "--python-expr", "import bpy; bpy.context.preferences.view.show_splash = False",
                          "--python", str(REPO / "tools" / "panel_screenshot.py"), "--",
                          str(addon_zip), str(raw), *flags], env, raw)
            image = Image.open(raw)
            width = image.size[0]
            image.crop((width - left, top, width, min(bottom, image.size[1]))).save(IMAGES / name)
            made.append(IMAGES / name)
    return made


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("plots", "demo", "feet", "panel", "all"))
    parser.add_argument("--render", action="store_true", help="demo, feet: render again even if the video is there")
    parser.add_argument("--blender", default="blender", help="panel: the Blender program (3.4+)")
    args = parser.parse_args(argv)
    made = []
    if args.what in ("plots", "all"):
        made += plots()
    if args.what in ("demo", "all"):
        made += demo(args.render)
    if args.what in ("feet", "all"):
        made += feet(args.render)
    if args.what in ("panel", "all"):
        made += panel(args.blender)
    for path in made:
        print("wrote", path.relative_to(REPO))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
