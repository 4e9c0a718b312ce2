"""Add-on preferences: install the heavy Python dependencies into Blender's Python.

One button runs pip (in a background thread, output streamed to the preferences as
progress) into Blender's user `scripts/modules` folder, which Blender puts on
`sys.path`. torch comes from the PyTorch index of the chosen build (CPU or CUDA), the
rest from PyPI; numpy is pinned to the version Blender ships so it is not replaced.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import threading
from pathlib import Path

import bpy
from bpy.props import EnumProperty, StringProperty

ADDON_PACKAGE = __package__

# import name -> pip requirement
DEPENDENCIES: dict[str, str] = {
    "torch": "torch>=2.1",
    "scipy": "scipy>=1.11",
    "librosa": "librosa>=0.10",
    "soundfile": "soundfile>=0.12",
    "safetensors": "safetensors>=0.4",
    "tqdm": "tqdm>=4.60",
}

TORCH_INDEXES: dict[str, str | None] = {
    "CPU": "https://download.pytorch.org/whl/cpu",
    "CUDA": "https://download.pytorch.org/whl/cu126",
    "PYPI": None,
}


def missing_dependencies() -> list[str]:
    """Import names of the required packages Blender's Python cannot find."""
    return [name for name in DEPENDENCIES if importlib.util.find_spec(name) is None]


def modules_dir(create: bool = True) -> Path:
    return Path(bpy.utils.user_resource("SCRIPTS", path="modules", create=create))


def pip_commands(build: str, target: Path, packages: list[str] | None = None) -> list[list[str]]:
    """The pip runs installing `packages` (import names; default all) into `target`."""
    import numpy

    names = packages if packages is not None else list(DEPENDENCIES)
    base = [sys.executable, "-m", "pip", "install", "--upgrade", "--target", str(target),
            "--disable-pip-version-check", "--no-input"]
    pin = f"numpy=={numpy.__version__}"
    commands = []
    if "torch" in names:
        index = TORCH_INDEXES[build]
        commands.append(base + (["--index-url", index] if index else []) + [DEPENDENCIES["torch"], pin])
    rest = [DEPENDENCIES[n] for n in names if n != "torch"]
    if rest:
        commands.append(base + rest + [pin])
    return commands


class InstallJob:
    """Run pip commands one after another in a thread; `lines` holds the output so far."""

    def __init__(self, commands: list[list[str]]):
        self.commands = commands
        self.lines: list[str] = []
        self.returncode: int | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> "InstallJob":
        if importlib.util.find_spec("pip") is None:
            self.commands.insert(0, [sys.executable, "-m", "ensurepip", "--upgrade"])
        self._thread.start()
        return self

    def _run(self) -> None:
        for command in self.commands:
            try:
                proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            except OSError as exc:
                self.lines.append(f"could not start {command[0]}: {exc}")
                self.returncode = 1
                return
            for line in proc.stdout:
                self.lines.append(line.rstrip())
            self.returncode = proc.wait()
            if self.returncode != 0:
                return

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self) -> None:
        self._thread.join()

    @property
    def status(self) -> str:
        """The latest meaningful pip line, e.g. 'Collecting torch' or 'Downloading ...'."""
        for line in reversed(self.lines):
            if line.strip():
                return line.strip()[:120]
        return "starting pip..."


def result_message(job: InstallJob) -> tuple[bool, str]:
    if job.returncode == 0:
        importlib.invalidate_caches()
        still = missing_dependencies()
        if still:
            return False, f"pip finished but these still do not import: {', '.join(still)}; restart Blender"
        return True, "dependencies installed: generation is ready"
    return False, f"pip failed ({job.status}); see the system console for the full output"


class DIFFSHEG_OT_install_dependencies(bpy.types.Operator):
    """Install torch, librosa, soundfile and the other packages into Blender's Python"""

    bl_idname = "diffsheg.install_dependencies"
    bl_label = "Install dependencies"

    _job: InstallJob | None = None
    _timer = None

    def invoke(self, context, event):
        prefs = context.preferences.addons[ADDON_PACKAGE].preferences
        self._job = InstallJob(pip_commands(prefs.torch_build, modules_dir())).start()
        prefs.install_status = "installing..."
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.5, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        prefs = context.preferences.addons[ADDON_PACKAGE].preferences
        job = InstallJob(pip_commands(prefs.torch_build, modules_dir())).start()
        job.wait()
        return self._report(context, job)

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        prefs = context.preferences.addons[ADDON_PACKAGE].preferences
        if not self._job.done:
            prefs.install_status = f"installing: {self._job.status}"
            if context.area is not None:
                context.area.tag_redraw()
            return {"RUNNING_MODAL"}
        context.window_manager.event_timer_remove(self._timer)
        return self._report(context, self._job)

    def _report(self, context, job: InstallJob):
        ok, message = result_message(job)
        print("\n".join(job.lines))
        context.preferences.addons[ADDON_PACKAGE].preferences.install_status = message
        self.report({"INFO"} if ok else {"ERROR"}, message)
        return {"FINISHED"} if ok else {"CANCELLED"}


class DIFFSHEG_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    torch_build: EnumProperty(name="torch build", default="CPU", items=[
        ("CPU", "CPU", "smaller download, runs everywhere"),
        ("CUDA", "CUDA 12.6 (NVIDIA GPU)", "fast generation on an NVIDIA GPU"),
        ("PYPI", "PyPI default", "the torch wheel PyPI gives this platform")])
    install_status: StringProperty(default="")

    def draw(self, context):
        layout = self.layout
        missing = missing_dependencies()
        if missing:
            layout.label(text=f"Missing: {', '.join(missing)}", icon="ERROR")
        else:
            layout.label(text="All dependencies are installed", icon="CHECKMARK")
        row = layout.row()
        row.prop(self, "torch_build")
        row.operator(DIFFSHEG_OT_install_dependencies.bl_idname, icon="IMPORT")
        layout.label(text=f"Target: {modules_dir(create=False)}")
        if self.install_status:
            layout.label(text=self.install_status)


CLASSES = (DIFFSHEG_OT_install_dependencies, DIFFSHEG_AP_preferences)

register, unregister = bpy.utils.register_classes_factory(CLASSES)
