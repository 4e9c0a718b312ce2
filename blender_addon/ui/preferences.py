"""Add-on preferences: the state of the Python packages generation runs on, and the
optional GPU support.

- The runtime packages (onnxruntime, soundfile, soxr, safetensors). In the Blender 4.2+
  extension they come with the zip, as wheels Blender installs offline (one zip per
  platform, see build_addon.py): the preferences only say whether they import, and that
  installing the zip of this platform again brings back any that is missing. The legacy
  add-on (Blender before 4.2) keeps a button that installs them with pip. numpy comes
  with Blender, except with the Blenders that Linux distributions build on the system's
  Python (Debian's 3.4): there the same button installs it too.
- Live's microphone: sounddevice needs the PortAudio library, which Linux provides as a
  system package (libportaudio2); the preferences say when a microphone cannot be used, and why.
- GPU support: torch, optional, for the official DiffSHEG checkpoints and NVIDIA GPUs. A
  button runs pip (in a background thread, its output streamed to the preferences) into
  Blender's user `scripts/modules` folder, which Blender puts on `sys.path`; torch comes
  from the PyTorch index of the chosen build (CPU or CUDA) and numpy is pinned to the
  version Blender ships so it is not replaced.

Whether each is there is environment.py's to say; nothing here imports those packages, so
the add-on registers with nothing but the standard library and bpy.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import bpy
from bpy.props import EnumProperty, StringProperty

from ..environment import (ADDON_PACKAGE, LIVE, RUNTIME, microphone_problem, missing_runtime, pip_installs_runtime,
                           runtime_problems, torch_installed)
from ..features.generate import BackgroundJob
from .widgets import draw_problems, wrapped_label

TORCH_REQUIREMENT = "torch>=2.1"
NUMPY_REQUIREMENT = "numpy>=1.26"  # where Blender's Python lacks it (else Blender's own is kept)

TORCH_INDEXES: dict[str, str | None] = {
    "CPU": "https://download.pytorch.org/whl/cpu",
    "CUDA": "https://download.pytorch.org/whl/cu126",
    "PYPI": None,
}


def modules_dir(create: bool = True) -> Path:
    return Path(bpy.utils.user_resource("SCRIPTS", path="modules", create=create))


def ensure_on_path(folder: Path) -> None:
    """Blender puts the user modules folder on sys.path only if it existed at start-up."""
    if folder.is_dir() and str(folder) not in sys.path:
        sys.path.append(str(folder))
    importlib.invalidate_caches()


def _pip_base(target: Path) -> list[str]:
    return [sys.executable, "-m", "pip", "install", "--upgrade", "--target", str(target),
            "--disable-pip-version-check", "--no-input"]


def _numpy_pin() -> str:
    """Blender's numpy, so pip keeps it; NUMPY_REQUIREMENT where there is none."""
    try:
        import numpy
    except ImportError:
        return NUMPY_REQUIREMENT
    return f"numpy=={numpy.__version__}"


def runtime_pip_commands(target: Path) -> list[list[str]]:
    """The pip run installing the runtime packages (and Live's) into `target` (the legacy
    add-on, or where numpy is missing)."""
    return [_pip_base(target) + list(LIVE.values()) + list(RUNTIME.values()) + [_numpy_pin()]]


def torch_pip_commands(build: str, target: Path) -> list[list[str]]:
    """The pip run installing torch of `build` (CPU, CUDA, PYPI) into `target`."""
    index = TORCH_INDEXES[build]
    return [_pip_base(target) + (["--index-url", index] if index else []) + [TORCH_REQUIREMENT, _numpy_pin()]]


def draw_microphone(layout, context) -> None:
    """Whether Live can use a microphone, and if not why (on Linux: the system's PortAudio
    library, libportaudio2) and how to fix it, wrapped to the preferences' width."""
    if importlib.util.find_spec("numpy") is None:
        return  # the runtime box says what is missing first
    problem = microphone_problem()
    if problem is None:
        layout.label(text="Live: a microphone can be used", icon="CHECKMARK")
        return
    wrapped_label(layout, context, f"Live cannot use a microphone: {problem}", icon="ERROR", beside_px=16)


class InstallJob(BackgroundJob):
    """Run pip commands one after another in a thread; `lines` holds the output so far."""

    def __init__(self, commands: list[list[str]]):
        super().__init__()
        self.commands = commands
        self.lines: list[str] = []
        self.returncode: int | None = None

    def start(self) -> "InstallJob":
        if importlib.util.find_spec("pip") is None:
            self.commands.insert(0, [sys.executable, "-m", "ensurepip", "--upgrade"])
        return super().start()

    def work(self) -> None:
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
    def status(self) -> str:
        """The latest meaningful pip line, e.g. 'Collecting torch' or 'Downloading ...'."""
        for line in reversed(self.lines):
            if line.strip():
                return line.strip()[:120]
        return "starting pip..."


def result_message(job: InstallJob, what: str) -> tuple[bool, str]:
    """`what`: 'runtime' or 'gpu'."""
    if job.returncode == 0:
        ensure_on_path(modules_dir(create=False))
        still = missing_runtime() if what == "runtime" else ([] if torch_installed() else ["torch"])
        if still:
            return False, f"pip finished but these still do not import: {', '.join(still)}; restart Blender"
        if what == "runtime":
            return True, "dependencies installed: generation is ready"
        return True, "GPU support installed: official checkpoints and CUDA GPUs can be used"
    return False, f"pip failed ({job.status}); see the system console for the full output"


class _PipOperator:
    """An operator running pip in the background (invoke: modal with progress; execute: blocking)."""

    what = "runtime"
    _job: InstallJob | None = None
    _timer = None

    def commands(self, prefs) -> list[list[str]]:
        raise NotImplementedError

    def invoke(self, context, event):
        prefs = context.preferences.addons[ADDON_PACKAGE].preferences
        self._job = InstallJob(self.commands(prefs)).start()
        prefs.install_status = "installing..."
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.5, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        prefs = context.preferences.addons[ADDON_PACKAGE].preferences
        job = InstallJob(self.commands(prefs)).start()
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
        ok, message = result_message(job, self.what)
        print("\n".join(job.lines))
        context.preferences.addons[ADDON_PACKAGE].preferences.install_status = message
        self.report({"INFO"} if ok else {"ERROR"}, message)
        return {"FINISHED"} if ok else {"CANCELLED"}


class DIFFSHEG_OT_install_dependencies(_PipOperator, bpy.types.Operator):
    """Install onnxruntime, soundfile, soxr and safetensors (and numpy where Blender's Python
    lacks it) into Blender's Python with pip (the legacy add-on; the 4.2+ extension brings them
    with its zip)"""

    bl_idname = "diffsheg.install_dependencies"
    bl_label = "Install dependencies"
    what = "runtime"

    def commands(self, prefs):
        return runtime_pip_commands(modules_dir())


class DIFFSHEG_OT_install_gpu_support(_PipOperator, bpy.types.Operator):
    """Install torch (CPU or CUDA build) into Blender's Python with pip: needed only for the
    official DiffSHEG checkpoints and for generating on an NVIDIA GPU"""

    bl_idname = "diffsheg.install_gpu_support"
    bl_label = "Install GPU support"
    what = "gpu"

    def commands(self, prefs):
        return torch_pip_commands(prefs.torch_build, modules_dir())


class DIFFSHEG_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    torch_build: EnumProperty(name="torch build", default="PYPI" if sys.platform == "darwin" else "CUDA", items=[
        ("CUDA", "CUDA 12.6 (NVIDIA GPU)", "generation on an NVIDIA GPU, and official checkpoints"),
        ("CPU", "CPU", "smaller download: official checkpoints on the CPU"),
        ("PYPI", "PyPI default", "the torch wheel PyPI gives this platform (macOS: CPU)")])
    install_status: StringProperty(default="")

    def draw(self, context):
        layout = self.layout
        box = layout.box()
        problems = runtime_problems()
        draw_problems(box, problems)
        if not problems:
            box.label(text="Generation is ready: " + ", ".join(RUNTIME) + " are installed", icon="CHECKMARK")
        if pip_installs_runtime():
            box.operator(DIFFSHEG_OT_install_dependencies.bl_idname, icon="IMPORT")

        draw_microphone(layout.box(), context)

        box = layout.box()
        if torch_installed():
            box.label(text="GPU support (torch) is installed", icon="CHECKMARK")
        else:
            box.label(text="GPU support (torch, optional): for official DiffSHEG checkpoints and NVIDIA GPUs",
                      icon="INFO")
        row = box.row()
        row.prop(self, "torch_build")
        row.operator(DIFFSHEG_OT_install_gpu_support.bl_idname, icon="IMPORT")
        box.label(text=f"Installs into: {modules_dir(create=False)}")
        if self.install_status:
            layout.label(text=self.install_status)


CLASSES = (DIFFSHEG_OT_install_dependencies, DIFFSHEG_OT_install_gpu_support, DIFFSHEG_AP_preferences)

register, unregister = bpy.utils.register_classes_factory(CLASSES)
