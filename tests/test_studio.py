"""Dialogue libraries on Ray (issue 28): batch_render.py --manifest, end to end on a real
Ray cluster started by the test and stopped after.

Ray's processes talk to each other over the node's address; the test runs them in a
network namespace of its own that has only the loopback interface (`unshare -n`), so
every connection stays on 127.0.0.1, and in a process namespace of its own (`-p -f
--mount-proc`), so `ray stop --force` and the killers see only the test's processes,
never a Ray the developer runs beside it. Six short lines of real speech, one of them a
corrupt audio file: five done with every output asked for, the sixth failed by name,
exit code 1; a rerun skips the five and rewrites nothing; a worker killed in the middle
of a line is retried and the batch ends with the outputs of a one-worker run; a driver
killed (SIGKILL) in the middle of the batch leaves only outputs of lines recorded done,
its Ray dies with it, and the next run does the rest, to the outputs of the batch that ran
through; a line's .blend finds the character's textures by their relative paths; a folder in
the way of one output fails that line alone, and once it is gone the next run puts the
output in place."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from addon_fixtures import REPO, SPEECH, SPEECH_2, append_face, bpy, cut_speech, import_beat_armature, reset_scene
from addon_fixtures import exit_before_blender_teardown  # noqa: F401 (fixture)
from system_tools import require_program

from diffsheg_core.manifest import ManifestError, read_manifest
from diffsheg_core.motion import Motion

pytest.importorskip("ray")
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the Ray test runs in network and process namespaces of its own (Linux, unshare)")

OUTPUTS = "blend;npz;arkit_json;csv;glb;fbx_unreal"
PORT = 6391
LONG_ID = "a_long_line_name_" + "é" * 91 + "x"  # 200 bytes in UTF-8: the longest id

# Runs in the namespace: a cluster, three batches, a worker killed during the third, a
# one-worker batch on the embedded default, the cluster stopped. argv: the manifest.
SCENARIO = r"""
set -u
ip link set lo up
export RAY_USAGE_STATS_ENABLED=0 RAY_AUTH_MODE=token RAY_AUTH_TOKEN=$(head -c 24 /dev/urandom | od -An -tx1 | tr -d ' \n')
batch() { "$PYTHON" "$REPO/batch_render.py" --manifest "$1" --output "$2" "${@:3}"; }
ray start --head --port=$PORT --num-cpus=2 --include-dashboard=false --disable-usage-stats > ray_start.log 2>&1
batch lines.csv first --ray-address 127.0.0.1:$PORT > first.log 2>&1; echo $? > first.rc
stamps() { find first -name 'line*' -printf '%p %T@\n' | sort; }
stamps > first.stamps
batch lines.csv first --ray-address 127.0.0.1:$PORT > again.log 2>&1; echo $? > again.rc
stamps > again.stamps
"$PYTHON" kill_one_worker.py > killed.log 2>&1 &
batch slow.csv killed --ray-address 127.0.0.1:$PORT > killed_run.log 2>&1; echo $? > killed.rc
wait
batch slow.csv one --workers 1 > one.log 2>&1; echo $? > one.rc
batch noblend.csv noblend --ray-address 127.0.0.1:$PORT > noblend.log 2>&1; echo $? > noblend.rc
mkdir -p blocked/b0.csv
for run in blocked still_blocked unblocked; do
  [ $run = unblocked ] && rmdir blocked/b0.csv
  batch two.csv blocked --ray-address 127.0.0.1:$PORT > $run.log 2>&1; echo $? > $run.rc
  cp blocked/report.csv $run.report.csv
done
ray stop --force > ray_stop.log 2>&1
"$PYTHON" kill_driver.py > driver_kill.log 2>&1; echo $? > driver_kill.rc
"""

# Runs lines.csv on a Ray of its own (two workers) into driver/, SIGKILLs the driver once
# a line is recorded done, notes what is left, tears the ledger's last line as a kill in
# the middle of an append would, runs the batch again, and waits for the killed driver's
# Ray processes to end. Writes driver_kill.json.
DRIVER_KILLER = r"""
import json, os, signal, subprocess, sys, time
from pathlib import Path

out = Path("driver")
command = [os.environ["PYTHON"], os.path.join(os.environ["REPO"], "batch_render.py"), "--manifest", "lines.csv",
           "--output", str(out), "--workers", "2"]
ledger = out / "done.jsonl"


def recorded():
    try:
        return [json.loads(l)["id"] for l in ledger.read_text().splitlines() if l.strip()]
    except (OSError, ValueError, KeyError):
        return []


def tree(root):
    # pid -> name (its command line's first word) of `root` and every process under it
    parents = {}
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
            name = os.path.basename(Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0].decode())
        except OSError:
            continue
        parents[int(pid)] = (int(stat.rsplit(")", 1)[1].split()[1]), name)
    found, todo = {}, [root]
    while todo:
        pid = todo.pop()
        found[pid] = parents.get(pid, (0, "?"))[1]
        todo += [c for c, (p, _) in parents.items() if p == pid and c not in found]
    return found


def alive(pids):
    left = []
    for pid in pids:
        try:
            if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] not in "ZX":
                left.append(pid)
        except OSError:
            pass
    return left


def files():
    return {str(p.relative_to(out)): [p.stat().st_mtime_ns, p.stat().st_size]
            for p in sorted(out.rglob("*")) if p.is_file()}


driver = subprocess.Popen(command, stdout=open("driver_first.log", "w"), stderr=subprocess.STDOUT)
deadline = time.time() + 600
while not recorded() and driver.poll() is None and time.time() < deadline:
    time.sleep(0.02)
ray = tree(driver.pid)
report = {"finished_first": driver.poll() is not None}
if not report["finished_first"]:
    os.kill(driver.pid, signal.SIGKILL)
killed_at = time.time()
driver.wait()
report.update(recorded=recorded(), ray=ray)
core = [pid for pid, name in ray.items() if pid != driver.pid and "agent" not in name.lower()]
while alive(core) and time.time() < killed_at + 30:
    time.sleep(0.1)
report["core_left"] = {pid: ray[pid] for pid in alive(core)}
report["core_seconds"] = time.time() - killed_at
report["after_kill"] = files()
report["ledger_after_kill"] = ledger.read_text()
with open(ledger, "ab") as fh:  # a driver killed while appending the next record
    fh.write(b'{"id": "line9", "key": "0123')
again = subprocess.run(command, capture_output=True, text=True)
report["resumed_rc"], report["resumed_log"] = again.returncode, again.stdout + again.stderr
report["after_resume"] = files()
while alive(ray) and time.time() < killed_at + 120:  # Ray's agents wait 60 s on the dead GCS
    time.sleep(0.5)
report["left"] = {pid: ray[pid] for pid in alive(ray)}
report["all_seconds"] = time.time() - killed_at
for pid in alive(ray):
    os.kill(pid, signal.SIGKILL)
Path("driver_kill.json").write_text(json.dumps(report, indent=1))
"""

# Kills the first worker seen running a line, once it has run for a second.
KILLER = r"""
import os, signal, time
deadline = time.time() + 120
while time.time() < deadline:
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                title = fh.read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if title.startswith("ray::_task"):
            time.sleep(1.0)
            os.kill(int(pid), signal.SIGKILL)
            print("killed", pid, flush=True)
            raise SystemExit(0)
    time.sleep(0.05)
print("no worker found", flush=True)
"""


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    """The scene, six lines (the third's audio corrupt), a slow two-line manifest, and the
    scenario's results."""
    unshare = require_program("unshare", "util-linux")
    work = tmp_path_factory.mktemp("studio")
    reset_scene(fps=24)
    import_beat_armature()
    append_face()
    (work / "tex").mkdir()
    skin = bpy.data.images.new("skin", 4, 4)
    skin.filepath_raw, skin.file_format = str(work / "tex" / "skin.png"), "PNG"
    skin.save()
    skin.use_fake_user = True
    bpy.ops.wm.save_as_mainfile(filepath=str(work / "character.blend"))
    skin.filepath = "//tex/skin.png"  # relative to the character's folder
    bpy.ops.wm.save_mainfile()
    audio = work / "audio"
    audio.mkdir()
    for i in range(6):
        cut_speech(audio, seconds=2.0, source=SPEECH if i % 2 else SPEECH_2, offset=3.0 + 2 * i, name=f"l{i}.wav")
    (audio / "corrupt.wav").write_bytes(b"RIFF\x00\x00\x00\x00WAVEfmt " + bytes(range(64)))
    character = f"character.blend,beat,{OUTPUTS}"
    # line2 asks for a video of a scene without a camera: it fails when it runs, alone
    rows = [f"line{i},audio/l{i}.wav,{i},{'calm' if i == 4 else ''},{character}{';mp4' if i == 2 else ''}"
            for i in range(6)]
    (work / "lines.csv").write_text("\n".join(["id,audio,seed,style,blend,preset,outputs", *rows]) + "\n")
    cut_speech(audio, seconds=8.0, source=SPEECH, offset=4.0, name="long1.wav")
    cut_speech(audio, seconds=8.0, source=SPEECH_2, offset=4.0, name="long2.wav")
    (work / "slow.csv").write_text("id,audio,seed,blend,preset,outputs\n"
                                   f"slow1,audio/long1.wav,7,{character}\nslow2,audio/long2.wav,8,{character}\n")
    (work / "two.csv").write_text("id,audio,seed,blend,preset,outputs\n"
                                  "b0,audio/l0.wav,1,character.blend,beat,npz;csv\n"
                                  "b1,audio/l1.wav,2,character.blend,beat,npz;csv\n")
    (work / "noblend.csv").write_text("id,audio,seed,outputs\n"  # no character: the motion's own files
                                      f"n0,audio/l0.wav,1,npz;csv;arkit_json\n{LONG_ID},audio/l1.wav,2,npz;csv\n")
    (work / "kill_one_worker.py").write_text(KILLER)
    (work / "kill_driver.py").write_text(DRIVER_KILLER)
    (work / "scenario.sh").write_text(SCENARIO)
    env = {**os.environ, "PYTHON": sys.executable, "REPO": str(REPO), "PORT": str(PORT)}
    proc = subprocess.run([unshare, "-n", "-p", "-f", "--mount-proc", "bash", "scenario.sh"], cwd=work, env=env, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return work


def _log(work, name: str) -> str:
    return (work / f"{name}.log").read_text()


def _rc(work, name: str) -> int:
    return int((work / f"{name}.rc").read_text())


def test_five_lines_done_one_failed_by_name(studio):
    log = _log(studio, "first")
    assert _rc(studio, "first") == 1, log
    assert log.strip().splitlines()[-1].startswith("5 done, 0 skipped (done before), 1 failed"), log[-1500:]
    out = studio / "first"
    for i in (0, 1, 3, 4, 5):
        for suffix in (".blend", ".npz", ".json", ".csv", ".glb", "_unreal.fbx"):
            assert (out / f"line{i}{suffix}").is_file(), (i, suffix)
        motion = Motion.load_npz(out / f"line{i}.npz")
        assert motion.meta["seed"] == i and motion.n_frames == 30
    assert Motion.load_npz(out / "line4.npz").meta["style_weights"] == {"calm": 1.0}
    assert not list(out.glob("line2*")) and not list(out.glob(".*partial*")) and not list(out.glob(".staged*"))
    report = (out / "report.csv").read_text().splitlines()
    assert report[1].startswith("line2,failed") and "line2" in report[1]
    assert "no camera" in report[1], report[1]
    assert "line2" in (out / "report.html").read_text()
    done = [json.loads(l)["id"] for l in (out / "done.jsonl").read_text().splitlines()]
    assert sorted(done) == ["line0", "line1", "line3", "line4", "line5"]


def test_a_rerun_skips_the_done_lines_and_rewrites_nothing(studio):
    log = _log(studio, "again")
    assert _rc(studio, "again") == 1  # line2 is still bad
    assert "6 lines: 5 done before, 1 to do" in log
    assert log.strip().splitlines()[-1].startswith("0 done, 5 skipped (done before), 1 failed"), log[-800:]
    stamps = (studio / "first.stamps").read_text()
    assert stamps == (studio / "again.stamps").read_text()  # no output written again
    assert stamps.count(".blend ") == 5


def test_a_killed_worker_is_retried_and_the_result_is_a_one_worker_runs(studio):
    assert _log(studio, "killed").startswith("killed"), _log(studio, "killed")
    assert _rc(studio, "killed") == 0, _log(studio, "killed_run")[-2000:]
    assert _rc(studio, "one") == 0, _log(studio, "one")[-2000:]
    for line in ("slow1", "slow2"):
        a = Motion.load_npz(studio / "killed" / f"{line}.npz")
        b = Motion.load_npz(studio / "one" / f"{line}.npz")
        np.testing.assert_array_equal(a.rotations, b.rotations)
        np.testing.assert_array_equal(a.face, b.face)
    assert not list((studio / "killed").glob(".*partial*"))


def test_the_check_pass_lists_every_bad_row_before_anything_runs(studio, tmp_path):
    (tmp_path / "loop.wav").symlink_to(tmp_path / "loop.wav")
    (tmp_path / "notes.blend").write_text("not a scene")
    bad = tmp_path / "bad.csv"
    bad.write_text("id,audio,blend,preset,seed,style,outputs\n"
                   f"a,{studio}/audio/l0.wav,{studio}/character.blend,beat,1,,blend\n"
                   f"b,{studio}/audio/missing.wav,{studio}/character.blend,beat,1,,blend\n"
                   f"c,{studio}/audio/l1.wav,{studio}/character.blend,no_such_preset,1,,blend\n"
                   f"a,{studio}/audio/l3.wav,{studio}/character.blend,beat,-4,,blend\n"
                   f"d,{studio}/audio/corrupt.wav,{studio}/character.blend,beat,1,,blend\n"
                   f"e,{tmp_path}/loop.wav,{studio}/character.blend,beat,1,,blend\n"
                   f"f,{studio}/audio/l4.wav,{tmp_path}/notes.blend,beat,1,,blend\n"
                   f"g,{studio}/audio/l5.wav,{studio}/character.blend,beat,1,calm=1e309,blend\n"
                   f"report,{studio}/audio/l5.wav,,,1,,csv\n"
                   f"{'x' * 201},{studio}/audio/l5.wav,,,1,,npz\n")
    proc = subprocess.run([sys.executable, str(REPO / "batch_render.py"), "--manifest", str(bad), "--check",
                           "--output", str(tmp_path / "out")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1 and not (tmp_path / "out").exists()
    assert "Traceback" not in proc.stderr and "unexpected" not in proc.stderr, proc.stderr
    for row, what in ((3, "missing.wav"), (4, "no_such_preset"), (5, "duplicate id"), (6, "the header is damaged"),
                      (7, "loop"), (8, "is not a Blender file"), (9, "calm"), (10, "writes itself"),
                      (11, "201 bytes long")):
        assert f"row {row}, column" in proc.stderr and what in proc.stderr, (row, what, proc.stderr)
    with pytest.raises(ManifestError):
        read_manifest(bad, presets=["beat"])
    good = tmp_path / "good.csv"
    good.write_text("\n".join(bad.read_text().splitlines()[:2]) + "\n")
    proc = subprocess.run([sys.executable, str(REPO / "batch_render.py"), "--manifest", str(good), "--check"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and "1 lines, all good" in proc.stdout, proc.stderr


def test_a_killed_driver_leaves_only_done_lines_and_the_next_run_resumes(studio):
    assert _rc(studio, "driver_kill") == 0, _log(studio, "driver_kill")[-2000:]
    report = json.loads((studio / "driver_kill.json").read_text())
    assert not report["finished_first"], (studio / "driver_first.log").read_text()[-2000:]
    done = report["recorded"]
    assert 1 <= len(done) < 5, done  # killed in the middle: some lines done, some not
    names = {n for n in report["ray"].values()}
    assert {"raylet", "gcs_server"} <= names, names  # it had started a Ray of its own
    # its Ray died with it: nothing but the driver could still write into the folder
    assert not report["core_left"], report["core_left"]
    print(f"driver killed with {len(done)} lines done; its raylet, GCS and workers gone after "
          f"{report['core_seconds']:.1f} s, all its Ray after {report['all_seconds']:.1f} s")
    assert not report["left"], report["left"]  # Ray's agents end by themselves too

    # what the kill left: outputs of recorded lines only, each line's all; unfinished
    # lines' files only in the staging folder
    ledger = [json.loads(l) for l in report["ledger_after_kill"].splitlines()]
    assert [e["id"] for e in ledger] == done
    outputs = {Path(o).name for e in ledger for o in e["outputs"]}
    visible = {f for f in report["after_kill"] if not f.startswith(".")}
    assert visible - {"done.jsonl"} <= outputs, visible - outputs
    hidden = {f for f in report["after_kill"] if f.startswith(".")}  # staged, or a staged file's temporary
    assert all(f.startswith((".staged-", "..staged-")) for f in hidden), hidden
    staged = {f.split(".", 2)[2] for f in hidden if f.startswith(".staged-")}  # .staged-<attempt>.<name>
    for e in ledger:  # recorded = every output in place (or, killed between the record and
        for o in e["outputs"]:  # the moves, still staged: the next run moves it)
            assert Path(o).name in visible or Path(o).name in staged, (e["id"], o)
    assert not [f for f in visible if "partial" in f]

    # the next run: the torn record ignored, the recorded lines skipped and untouched,
    # the rest done; nothing staged or partial left
    assert report["resumed_rc"] == 1, report["resumed_log"][-2000:]  # line2 still has no camera
    log = report["resumed_log"]
    assert f"6 lines: {len(done)} done before, {6 - len(done)} to do" in log, log[-2000:]
    assert f"{5 - len(done)} done, {len(done)} skipped (done before), 1 failed" in log, log[-2000:]
    after = report["after_resume"]
    for name in outputs:
        if name in report["after_kill"]:
            assert after[name] == report["after_kill"][name], name  # not written again
        else:  # killed between its record and its moves: the next run moved it in from staging
            assert name in after and name in staged, name
    assert not [f for f in after if f.startswith(".") or "partial" in f], sorted(after)
    out = studio / "driver"
    records = (out / "done.jsonl").read_text().splitlines()
    assert records[len(done)].startswith('{"id": "line9"') and len(records) == 6  # the torn line kept apart
    assert sorted(json.loads(l)["id"] for i, l in enumerate(records) if i != len(done)) == \
        ["line0", "line1", "line3", "line4", "line5"]
    # the outputs of the batch that ran through (the same seeds; a cluster, not two workers)
    for i in (0, 1, 3, 4, 5):
        for suffix in (".json", ".csv"):
            a, b = (out / f"line{i}{suffix}").read_bytes(), (studio / "first" / f"line{i}{suffix}").read_bytes()
            assert a == b, (i, suffix)
        with np.load(out / f"line{i}.npz") as a, np.load(studio / "first" / f"line{i}.npz") as b:
            assert sorted(a.files) == sorted(b.files)
            for member in a.files:
                assert a[member].tobytes() == b[member].tobytes(), (i, member)
    assert not list(out.glob("line2*"))


def test_lines_without_a_character_write_the_motions_own_files(studio):
    """A manifest with no .blend anywhere (issue 43, defect 1): the lines' npz, csv and
    ARKit JSON are written, the longest id (200 bytes) too."""
    log = _log(studio, "noblend")
    assert _rc(studio, "noblend") == 0, log[-2000:]
    assert "2 done, 0 skipped (done before), 0 failed" in log, log[-2000:]
    out = studio / "noblend"
    for name in ("n0.npz", "n0.csv", "n0.json", f"{LONG_ID}.npz", f"{LONG_ID}.csv"):
        assert (out / name).is_file() and (out / name).stat().st_size, name
    assert Motion.load_npz(out / "n0.npz").n_frames == 30
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []
    done = [json.loads(l)["id"] for l in (out / "done.jsonl").read_text(encoding="utf-8").splitlines()]
    assert sorted(done) == sorted(["n0", LONG_ID])


def test_the_embedded_ray_stays_on_loopback(studio):
    """The Ray started on this machine (the `one` run) listens on 127.0.0.1 and looks for no
    network address (issue 43, defect 12)."""
    log = _log(studio, "one")
    assert "2 done, 0 skipped" in log and "8.8.8.8" not in log and "external connectivity" not in log, log[-2000:]


def test_a_lines_blend_finds_the_characters_textures(studio):
    """The character's image by a path relative to its .blend (//tex/skin.png): the line's
    .blend, saved in another folder, still finds it."""
    bpy.ops.wm.open_mainfile(filepath=str(studio / "first" / "line0.blend"))
    skin = bpy.data.images["skin"]
    assert skin.filepath.startswith("//"), skin.filepath
    assert Path(bpy.path.abspath(skin.filepath)).resolve() == (studio / "tex" / "skin.png").resolve()
    assert Path(bpy.path.abspath(skin.filepath)).is_file()


def test_an_output_that_cannot_be_put_in_place_fails_its_line_alone(studio):
    """A folder at b0.csv: b0 fails with that error and b1 is done; the next run (still
    blocked) does b0 again, to the same error; the folder removed, the run after puts b0.csv
    in place and everything is done."""
    log = _log(studio, "blocked")
    assert _rc(studio, "blocked") == 1, log[-2000:]
    assert log.strip().splitlines()[-1].startswith("1 done, 0 skipped (done before), 1 failed"), log[-2000:]
    assert "b0: failed: cannot put b0.csv in place" in log and "Is a directory" in log, log[-2000:]
    row = next(r for r in (studio / "blocked.report.csv").read_text().splitlines() if r.startswith("b0,"))
    assert "failed" in row and "b0.csv" in row, row
    log = _log(studio, "still_blocked")
    assert _rc(studio, "still_blocked") == 1, log[-2000:]
    assert "b0: cannot put b0.csv in place" in log and "2 lines: 1 done before, 1 to do" in log, log[-2000:]
    assert log.strip().splitlines()[-1].startswith("0 done, 1 skipped (done before), 1 failed"), log[-2000:]
    log = _log(studio, "unblocked")
    assert _rc(studio, "unblocked") == 0, log[-2000:]
    assert "2 lines: 2 done before, 0 to do" in log, log[-2000:]
    out = studio / "blocked"
    for name in ("b0.npz", "b0.csv", "b1.npz", "b1.csv"):
        assert (out / name).is_file() and (out / name).stat().st_size, name
    assert (out / "b0.csv").read_text().splitlines()[0] == (out / "b1.csv").read_text().splitlines()[0]
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]
