"""Nothing the user had is lost and nothing silently wrong comes out: damaged models are
refused when they load, non-finite motion before anything is written, outputs never
overwrite an input and are written atomically, odd inputs get messages that name them."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from conftest import random_bundle

from diffsheg_core import AudioError, CheckpointError, DiffshegError, generate
from diffsheg_core.audio import load_audio
from diffsheg_core.checkpoints import DEFAULT_WEIGHTS, load_model, read_safetensors, write_safetensors
from diffsheg_core.errors import AudioWarning
from diffsheg_core.motion import Motion

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def speech(data_dir, tmp_path_factory) -> Path:
    """Three seconds of real speech."""
    samples, rate = sf.read(data_dir / "audio" / "2_scott_0_4_4.wav", dtype="float32")
    path = tmp_path_factory.mktemp("speech") / "talk.wav"
    sf.write(path, samples[: 3 * rate], rate)
    return path


@pytest.fixture(scope="module")
def default_file():
    return read_safetensors(DEFAULT_WEIGHTS, "")


def damaged_copy(default_file, path: Path, name: str, change) -> Path:
    """The bundled file with tensor `name` changed. A network weight its ONNX graph holds is
    damaged there (where the file stores it) and the graph's name for it is returned with it."""
    import onnx
    from onnx import numpy_helper

    meta, tensors = default_file
    if name in tensors:
        return write_safetensors({**tensors, name: change(tensors[name].copy())}, meta, path)
    for graph in ("onnx.expression", "onnx.gesture"):
        proto = onnx.load_from_string(tensors[graph].tobytes())
        for init in proto.graph.initializer:
            if init.name in (name, name + ".fp16"):
                init.CopyFrom(numpy_helper.from_array(change(numpy_helper.to_array(init).copy()), init.name))
                damaged = np.frombuffer(proto.SerializeToString(), np.uint8)
                return write_safetensors({**tensors, graph: damaged}, meta, path)
    raise KeyError(name)


def cli(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "diffsheg_core", "generate", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


def nan_at_first(values: np.ndarray) -> np.ndarray:
    values.flat[0] = np.nan
    return values


@pytest.mark.parametrize("name,change,match", [
    ("model.encoder_ges.out.weight", nan_at_first, "encoder_ges.out.weight \\(NaN or infinite\\)"),
    ("model.encoder_exp.joint_embed.weight", lambda v: (v.astype(np.float32) * 1e30).astype(np.float32),
     "encoder_exp.joint_embed.weight \\(values up to"),
    ("model.encoder_low.PE.pe", nan_at_first, "model.encoder_low.PE.pe \\(NaN or infinite\\)"),
    ("norm.std", lambda v: np.full_like(v, np.inf), "norm.std \\(NaN or infinite\\)"),
])
def test_damaged_weights_are_refused_when_the_model_loads(default_file, tmp_path, speech, name, change, match):
    path = damaged_copy(default_file, tmp_path / "damaged.safetensors", name, change)
    with pytest.raises(CheckpointError, match=match) as err:
        load_model(path)
    assert str(path) in str(err.value) and "again" in str(err.value)
    out = tmp_path / "motion.npz"
    result = cli(str(speech), "--checkpoint", str(path), "-o", str(out))
    assert result.returncode == 2 and "damaged weights" in result.stderr
    assert "Traceback" not in result.stderr and not out.exists()


def test_non_finite_motion_is_refused_before_anything_is_written(speech):
    bundle = random_bundle(graphs=False)
    weights = dict(bundle.weights)
    weights["encoder_ges.out.bias"] = np.full_like(weights["encoder_ges.out.bias"], np.nan)
    with pytest.raises(DiffshegError, match="NaN or infinite motion .*nothing was written"):
        generate(speech, model=replace(bundle, weights=weights), steps=2)


def test_bad_checkpoint_metadata_names_the_field(default_file, tmp_path):
    meta, tensors = default_file
    path = write_safetensors(tensors, {**meta, "info": "{not json"}, tmp_path / "bad_meta.safetensors")
    with pytest.raises(CheckpointError, match="metadata 'info' is not valid JSON"):
        load_model(path)


def test_an_output_that_is_an_input_is_refused_and_the_input_kept(speech, tmp_path):
    talk = tmp_path / "talk.wav"
    talk.write_bytes(speech.read_bytes())
    before = talk.read_bytes()
    for option in ("-o", "--bvh", "--arkit-json", "--csv"):
        result = cli(str(talk), *(["-o", str(tmp_path / "m.npz")] if option != "-o" else []), option, str(talk))
        assert result.returncode == 2 and "is an input of this run" in result.stderr, option
        assert "Traceback" not in result.stderr
    assert talk.read_bytes() == before
    result = cli(str(talk), "-o", str(tmp_path / "m.npz"), "--bvh", str(tmp_path / "m.npz"))
    assert result.returncode == 2 and "named twice" in result.stderr


def test_the_bundled_model_is_an_input_even_when_not_named(speech, tmp_path):
    import hashlib

    before = hashlib.sha256(DEFAULT_WEIGHTS.read_bytes()).hexdigest()
    backup = shutil.copy(DEFAULT_WEIGHTS, tmp_path / "backup.safetensors")  # restored if the refusal fails
    try:
        result = cli(str(speech), "-o", str(DEFAULT_WEIGHTS))
    finally:
        if hashlib.sha256(DEFAULT_WEIGHTS.read_bytes()).hexdigest() != before:
            shutil.copy(backup, DEFAULT_WEIGHTS)
            pytest.fail("-o overwrote the bundled model (restored from a copy)")
    assert result.returncode == 2 and "is an input of this run" in result.stderr
    assert str(DEFAULT_WEIGHTS) in result.stderr and "Traceback" not in result.stderr


def test_statistics_and_hubert_files_are_inputs(speech, data_dir, golden_dir, tmp_path):
    from test_checkpoints import golden_official_file

    official = golden_official_file(golden_dir, tmp_path)
    stats = tmp_path / "stats"
    shutil.copytree(data_dir / "beat", stats)
    shutil.copy(stats / "facial51_std.npy", tmp_path)  # beside the checkpoint: read when no --stats
    hubert = tmp_path / "hubert"
    (hubert / "sub").mkdir(parents=True)
    (hubert / "sub" / "config.json").write_text("{}")
    for extra, output in ([], tmp_path / "facial51_std.npy"), (["--stats", str(stats)], stats / "axis_angle_std.npy"), \
            (["--hubert", str(hubert)], hubert / "sub" / "config.json"):
        before = output.read_bytes()
        result = cli(str(speech), "--model", str(official), *extra, "-o", str(output))
        assert result.returncode == 2 and "is an input of this run" in result.stderr, (extra, result.stderr)
        assert output.read_bytes() == before


def test_a_folder_as_output_is_refused_before_generating(speech, tmp_path):
    result = cli(str(speech), "-o", str(tmp_path))
    assert result.returncode == 2 and "is a folder" in result.stderr
    assert "frames at" not in result.stdout  # refused up front: nothing was generated


@pytest.fixture(scope="module")
def motion(speech) -> Motion:
    return generate(speech, steps=2)


@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()])
def test_a_failed_save_leaves_the_previous_file_byte_for_byte(motion, tmp_path, monkeypatch, failure):
    """A full disk or Ctrl-C in the middle of writing: the old file stays, no partial file is left."""
    from diffsheg_core import motion as motion_module

    path = motion.save_npz(tmp_path / "talk.npz")
    before = path.read_bytes()

    def failing_write(fh, arrays):
        fh.write(b"PK\x03\x04 half an archive")
        raise failure

    monkeypatch.setattr(motion_module, "write_npz", failing_write)
    expected = DiffshegError if isinstance(failure, OSError) else KeyboardInterrupt
    with pytest.raises(expected) as err:
        motion.save_npz(path)
    if expected is DiffshegError:
        assert str(path) in str(err.value) and "unchanged" in str(err.value)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["talk.npz"]


FILE_LIMIT = """
import resource, signal, sys
from diffsheg_core.errors import DiffshegError
from diffsheg_core.motion import Motion
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # past the limit, a write fails with EFBIG as on a full disk
resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
try:
    Motion.load_npz(sys.argv[1]).save_npz(sys.argv[2])
except DiffshegError as exc:
    print(exc)
"""


@pytest.mark.skipif(not hasattr(__import__("signal"), "SIGXFSZ"), reason="file size limits are POSIX")
def test_a_full_disk_while_writing_an_npz_gives_its_message_alone(motion, tmp_path):
    """The archive is closed when a write fails: no "Exception ignored in ZipFile.__del__"."""
    source = motion.save_npz(tmp_path / "take.npz")
    assert source.stat().st_size > 40_000
    result = subprocess.run([sys.executable, "-c", FILE_LIMIT, str(source), str(tmp_path / "out.npz")],
                            capture_output=True, text=True, timeout=120, cwd=REPO)
    assert result.returncode == 0 and "could not be written" in result.stdout, result
    assert result.stderr == "" and sorted(p.name for p in tmp_path.iterdir()) == ["take.npz"]


def test_every_writer_replaces_its_file_only_when_complete(motion, tmp_path):
    from diffsheg_core.bvh import write_bvh
    from diffsheg_core.motion import write_arkit_json, write_livelink_csv

    for write, name in ((write_bvh, "m.bvh"), (write_arkit_json, "m.json"), (write_livelink_csv, "m.csv"),
                        (lambda m, p: m.save_npz(p), "m.npz")):
        path = tmp_path / name
        path.write_text("the previous take")
        write(motion, path)
        assert path.stat().st_size > 100 and oct(path.stat().st_mode & 0o777) != "0o600"
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".partial")]


def test_seeds_beyond_64_bits_are_used_as_given(speech):
    a = generate(speech, steps=2, seed=5)
    b = generate(speech, steps=2, seed=5 + 2**64)
    assert b.meta["seed"] == 5 + 2**64 and not np.allclose(a.rotations, b.rotations)


def test_odd_audio_files_are_named_for_what_they_are(tmp_path, speech):
    fifo = tmp_path / "pipe.wav"
    os.mkfifo(fifo)
    loop = tmp_path / "loop.wav"
    loop.symlink_to(tmp_path / "loop2.wav")
    (tmp_path / "loop2.wav").symlink_to(loop)
    folder = tmp_path / "folder.wav"
    folder.mkdir()
    dangling = tmp_path / "gone.wav"
    dangling.symlink_to(tmp_path / "deleted.wav")
    for path, match in ((fifo, "not a regular file"), (loop, "symbolic link that leads back to itself"),
                        (dangling, "symbolic link to nothing"), (folder, "is a folder")):
        with pytest.raises(AudioError, match=match):
            load_audio(path)


def test_a_symbolic_link_loop_as_audio_is_named_in_one_line(speech, tmp_path):
    """Issue 43 (a): `generate loop.wav` where loop.wav -> loop.wav ended in `RuntimeError:
    Symlink loop` from the output check (Python 3.11's Path.resolve)."""
    loop = tmp_path / "loop.wav"
    loop.symlink_to(loop)
    result = cli(str(loop), "-o", str(tmp_path / "out.npz"))
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert result.stderr.strip().splitlines() == [
        f"error: audio file '{loop}' is a symbolic link that leads back to itself (directly or through other "
        "links, a loop): point it at a real file, or give another path"]
    assert not (tmp_path / "out.npz").exists()


def test_a_symbolic_link_loop_as_output_is_refused_before_generating(speech, tmp_path):
    """An output that is a loop, or lies in a folder that is one, for each output option."""
    (tmp_path / "self.npz").symlink_to(tmp_path / "self.npz")
    (tmp_path / "a.bvh").symlink_to(tmp_path / "b.bvh")
    (tmp_path / "b.bvh").symlink_to(tmp_path / "a.bvh")
    (tmp_path / "loopdir").symlink_to(tmp_path / "loopdir")
    for option, output, problem in (("-o", tmp_path / "self.npz", "is a symbolic link that leads back to itself"),
                                    ("--bvh", tmp_path / "a.bvh", "is a symbolic link that leads back to itself"),
                                    ("-o", tmp_path / "loopdir" / "m.npz", "goes through a symbolic link that "
                                                                           "leads back to itself"),
                                    ("--csv", tmp_path / "loopdir" / "face.csv", "goes through a symbolic link")):
        rest = [] if option == "-o" else ["-o", str(tmp_path / "m.npz")]
        result = cli(str(speech), *rest, option, str(output))
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: output '{output}' {problem}"), lines
        assert "frames at" not in result.stdout  # refused up front: nothing was generated
    assert not (tmp_path / "m.npz").exists() and (tmp_path / "self.npz").is_symlink()


def test_resolve_path_follows_links_and_names_a_loop(speech, tmp_path):
    """files.resolve_path, the one place a user's path is followed (the manifest reader uses it too)."""
    from diffsheg_core.files import atomic_write, check_output, resolve_path

    link = tmp_path / "link.wav"
    link.symlink_to(speech)
    assert resolve_path(link, "audio file") == speech.resolve()
    assert resolve_path(tmp_path / "new" / "m.npz") == tmp_path.resolve() / "new" / "m.npz"  # need not exist
    loop = tmp_path / "loop.wav"
    loop.symlink_to(tmp_path / "loop2.wav")
    (tmp_path / "loop2.wav").symlink_to(loop)
    with pytest.raises(DiffshegError, match=f"^line 3 audio '{loop}' is a symbolic link that leads back to itself"):
        resolve_path(loop, "line 3 audio")
    with pytest.raises(AudioError, match="audio file .* leads back to itself"):
        resolve_path(str(loop), "audio file", AudioError)
    with pytest.raises(DiffshegError, match="goes through a symbolic link that leads back to itself"):
        resolve_path(loop / "inside.wav")
    with pytest.raises(DiffshegError, match="output .* leads back to itself"):
        check_output(loop)
    with pytest.raises(DiffshegError, match="output .* leads back to itself"):
        with atomic_write(loop) as fh:
            fh.write(b"never")
    assert loop.is_symlink() and not list(tmp_path.glob(".*partial"))


def test_a_wav_cut_short_of_its_header_is_generated_with_a_warning(speech, tmp_path):
    data = speech.read_bytes()
    cut = tmp_path / "cut.wav"
    cut.write_bytes(data[: len(data) // 2])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        motion = generate(cut, steps=2)
    messages = [str(w.message) for w in caught if issubclass(w.category, AudioWarning)]
    assert messages and "cut short" in messages[0] and "3.0 s" in messages[0] and "1.5 s" in messages[0]
    assert motion.n_frames == 22
    result = cli(str(cut), "-o", str(tmp_path / "m.npz"), "--steps", "2")
    assert result.returncode == 0 and "warning: " in result.stderr and "cut short" in result.stderr


PEAK = """
import resource, sys
import diffsheg_core
motion = diffsheg_core.generate(sys.argv[1], steps=2)
print(motion.n_frames, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def test_long_audio_is_generated_in_bounded_memory(data_dir, tmp_path):
    """Real speech repeated to 5 and 20 minutes: the features are computed piece by piece as
    the sampler needs them, so the peak grows only by the motion itself (measured: 450 and
    461 MB; before, 21 MB more per minute of audio)."""
    samples, rate = sf.read(data_dir / "audio" / "2_scott_0_3_3.wav", dtype="float32")
    peaks = {}
    for minutes in (5, 20):
        path = tmp_path / f"talk_{minutes}min.wav"
        sf.write(path, np.resize(samples, minutes * 60 * rate), rate, subtype="PCM_16")
        result = subprocess.run([sys.executable, "-c", PEAK, str(path)], capture_output=True, text=True,
                                timeout=600, cwd=REPO)
        assert result.returncode == 0, result.stderr
        frames, kilobytes = map(int, result.stdout.split())
        assert frames == minutes * 60 * 15
        peaks[minutes] = kilobytes / 1024
        path.unlink()
    assert peaks[20] - peaks[5] < 60, peaks  # the 15 minutes of motion are about 25 MB


def test_pieces_of_a_long_recording_give_the_features_of_the_whole(data_dir, monkeypatch):
    from diffsheg_core import pipeline, speech_features
    from diffsheg_core.conditioning import SpeechFeatures
    from diffsheg_core.runtime.backends import open_network

    path = data_dir / "audio" / "2_scott_0_3_3.wav"  # 68 s
    bundle = load_model()
    network = open_network(bundle)
    whole = speech_features.speech_features(bundle, network, load_audio(path))
    monkeypatch.setattr(speech_features, "PIECE_SECONDS", 20)  # four pieces
    pieces = list(speech_features.speech_chunks(bundle, network, pipeline.open_speech(path)))
    assert [len(p) for p in pieces] == [300, 300, 300, 120]
    joined = SpeechFeatures.join(pieces)
    assert np.abs(joined.mel - whole.mel).max() < 1e-6 * np.abs(whole.mel).max()
    assert np.abs(joined.speech - whole.speech).max() < 2e-3  # phone probabilities


def test_the_motion_records_what_was_odd_about_the_audio(speech, tmp_path):
    data = speech.read_bytes()
    cut = tmp_path / "cut.wav"
    cut.write_bytes(data[: len(data) // 2])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert "cut short" in generate(cut, steps=2).meta["warnings"][0]
    assert generate(speech, steps=2).meta["warnings"] == []
