"""The trainer on a tiny fixture cut from the real take 2_scott_0_1_1 (BEAT motion
capture and its audio): overfitting, resume after kill -9, torchrun with two processes."""

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
import torch

from diffsheg_core.bvh import read_bvh, write_bvh_data
from diffsheg_core.checkpoints import load_model
from diffsheg_core.training.data.beat import read_gesture
from diffsheg_core.errors import DiffshegError
from diffsheg_core.training.metrics import layout_array
from diffsheg_core.motion import Motion, write_livelink_csv
from diffsheg_core.rigs import ARKIT51
from diffsheg_core.pipeline import generate
from diffsheg_core.diffusion import Schedule
from diffsheg_core.torch_layer.model import UniEG
from diffsheg_core.training.train import (
    LOG_FILE, MODEL_FILE, STATE_FILE, SUMMARY_FILE, Dist, TrainConfig, Trainer, diffsheg_loss,
    fine_tuning_statistics, read_config_file, train, x0_term_weight,
)
from diffsheg_core.training.data import NormStats

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
REPO = Path(__file__).resolve().parents[1]
TINY = {"latent": 32, "layers": 1, "ff": 64, "heads": 4, "style_dim": 2}


def write_take(folder: Path, name: str, start: float, seconds: float, face: bool = False) -> None:
    """`name`.wav and `name`.bvh (15 fps) of the real take from `start`; with `face`, also
    `name`.csv, Live Link Face weights (smooth synthetic curves: no real ARKit capture here)."""
    y, sr = sf.read(DATA / "beat2" / "2_scott_0_1_1.wav", dtype="float32")
    folder.mkdir(parents=True, exist_ok=True)
    sf.write(folder / f"{name}.wav", y[int(start * sr): int((start + seconds) * sr)], sr)
    data = read_bvh(DATA / "beat" / "2_scott_0_1_1.bvh", fps=15.0)
    out = data.copy()
    out.frames = data.frames[1 + int(round(start * 15)): 1 + int(round((start + seconds) * 15))]
    write_bvh_data(out, folder / f"{name}.bvh")
    if face:
        n = int(round(seconds * 60))
        t = np.arange(n)[:, None] / 60
        k = np.arange(len(ARKIT51))[None, :]
        weights = 0.3 + 0.2 * np.sin(2 * np.pi * (0.5 + 0.05 * k) * t + k)
        write_livelink_csv(Motion(fps=60.0, rig="beat", joint_names=[], rotations=np.zeros((n, 0, 3)),
                                  face_names=list(ARKIT51), face=weights), folder / f"{name}.csv")


def config(root: Path, out: Path, **over) -> dict:
    cfg = {"data": {"kind": "folder", "root": str(root), "clip_len": 16, "stride": 4,
                    "val_fraction": 0.0, "cache_dir": str(root / "cache")},
           "model": dict(TINY), "out_dir": str(out), "steps": 30, "batch_size": 4, "lr": 1e-3,
           "log_every": 1, "checkpoint_every": 10, "validate_every": 1000}
    cfg.update(over)
    return cfg


def read_log(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / LOG_FILE).read_text().splitlines()]


@pytest.fixture(scope="module")
def small_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("takes")
    write_take(root, "talk", 12.0, 3.0)
    return root


def _run(args: list[str], **kw) -> subprocess.Popen:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    return subprocess.Popen([sys.executable, *args], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, **kw)


def test_resume_after_kill_continues_the_same_loss_curve(small_root, tmp_path):
    straight, killed = tmp_path / "straight", tmp_path / "killed"
    for run in (straight, killed):
        (tmp_path / f"{run.name}.json").write_text(json.dumps(config(small_root, run)))
    ref = _run(["-m", "diffsheg_core", "train", "--config", str(tmp_path / "straight.json")])
    assert ref.wait(timeout=300) == 0, ref.stdout.read()

    proc = _run(["-m", "diffsheg_core", "train", "--config", str(tmp_path / "killed.json")])
    state = killed / STATE_FILE
    while proc.poll() is None:
        if state.is_file() and torch.load(state, weights_only=True)["step"] >= 20:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "training ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    saved = torch.load(state, weights_only=True)["step"]
    assert saved in (20, 30)

    resumed = _run(["-m", "diffsheg_core", "train", "--config", str(tmp_path / "killed.json")])
    out = resumed.communicate(timeout=300)[0]
    assert resumed.returncode == 0, out
    assert f"resuming at step {saved}" in out
    a = [r["loss"] for r in read_log(straight) if "loss" in r]
    b = [r["loss"] for r in read_log(killed) if "loss" in r]
    assert len(a) == len(b) == 30
    np.testing.assert_allclose(b, a, rtol=1e-5)
    assert json.loads((killed / SUMMARY_FILE).read_text())["step"] == 30


def test_two_processes_with_torchrun_keep_identical_parameters(small_root, tmp_path):
    run = tmp_path / "ddp"
    (tmp_path / "ddp.json").write_text(json.dumps(config(small_root, run, steps=6, checkpoint_every=100,
                                                          sampling={"eta": 0.5})))
    proc = _run(["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                 "-m", "diffsheg_core.training.train", "--config", str(tmp_path / "ddp.json"), "--device", "cpu"])
    out = proc.communicate(timeout=300)[0]
    assert proc.returncode == 0, out
    summary = json.loads((run / SUMMARY_FILE).read_text())
    assert summary["world_size"] == 2 and summary["step"] == 6
    first, second = summary["param_checksums"]
    assert first == second
    bundle = load_model(run / MODEL_FILE)
    assert bundle.config.layout == "beat" and bundle.config.latent == 32
    assert bundle.sampling.eta == 0.5 and bundle.sampling.overlap == 4  # the preset, with the override


def test_configuration_files_and_errors(small_root, tmp_path):
    toml = tmp_path / "run.toml"
    toml.write_text(f'steps = 5\nlr = 0.001\n[data]\nkind = "folder"\nroot = "{small_root}"\n'
                    '[model]\nlatent = 32\n')
    cfg = TrainConfig.from_dict(read_config_file(toml))
    assert cfg.steps == 5 and cfg.data.kind == "folder" and cfg.model == {"latent": 32}
    with pytest.raises(DiffshegError, match="unknown training settings: stpes"):
        TrainConfig.from_dict({"stpes": 5})
    with pytest.raises(DiffshegError, match="unknown data settings: rot"):
        TrainConfig.from_dict({"data": {"rot": "x"}})
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(DiffshegError, match="not valid JSON"):
        read_config_file(bad)
    with pytest.raises(DiffshegError, match="style class 0, but the model has only 0"):
        train(TrainConfig.from_dict(config(small_root, tmp_path / "x", model={**TINY, "style_dim": 0})))
    with pytest.raises(DiffshegError, match="x0_weighting must be one of abar, none"):
        train(TrainConfig.from_dict(config(small_root, tmp_path / "x", x0_weighting="snr")))
    with pytest.raises(DiffshegError, match="sampling settings .*etaa"):
        train(TrainConfig.from_dict(config(small_root, tmp_path / "x", sampling={"etaa": 1.0})))
    with pytest.raises(DiffshegError, match="export_dtype must be one of float32, float16"):
        train(TrainConfig.from_dict(config(small_root, tmp_path / "x", export_dtype="int8")))


def test_x0_terms_are_weighted_by_abar():
    """The x0 error is the noise error times sqrt(1/abar - 1): weighted by abar, the x0 terms
    never outgrow the noise term, and keep full weight at low noise."""
    schedule = Schedule.linear()
    index = torch.tensor([0, 500, 999])
    like = torch.zeros(3, 8, 4)
    w = x0_term_weight(schedule, index, like, "abar").flatten()
    np.testing.assert_allclose(w.numpy(), schedule.alphas_cumprod[[0, 500, 999]], rtol=1e-6)
    assert w[0] > 0.999 and w[2] < 1e-4
    scale = torch.from_numpy(np.sqrt(1 / schedule.alphas_cumprod - 1)).float()[index]
    assert float((w * scale**2).max()) <= 1.0  # squared x0 error per unit noise error, weighted
    assert torch.equal(x0_term_weight(schedule, index, like, "none").flatten(), torch.ones(3))


OVERFIT = {"latent": 256, "layers": 1, "ff": 256, "heads": 4, "style_dim": 1, "log_mel": True}


def test_tiny_model_overfits_a_clip_and_reproduces_it(tmp_path):
    root = tmp_path / "clip"
    write_take(root, "talk", 12.0, 16 / 15, face=True)
    write_take(root, "talk_again", 12.0, 16 / 15, face=True)  # the same clip, as validation
    (root / "train_test_split.csv").write_text("id,type\ntalk,train\ntalk_again,val\n")
    cfg = config(root, tmp_path / "run", model=OVERFIT, steps=400, batch_size=16, lr=2e-3, ema_decay=0.95,
                 log_every=50, checkpoint_every=400, validate_every=400)
    cfg["data"].update(stride=16, stats=str(DATA / "beat"))
    cfg.update(export=str(tmp_path / "exported.safetensors"), export_dtype="float16", card={"licence": "test"})
    torch.set_num_threads(1)
    summary = train(TrainConfig.from_dict(cfg))
    assert summary["step"] == 400
    val = [r["val_loss"] for r in read_log(tmp_path / "run") if "val_loss" in r]
    assert val[-1] < val[0] / 10

    bundle = load_model(tmp_path / "run" / MODEL_FILE)
    assert bundle.trained and bundle.layout.name == "beat"
    exported = load_model(summary["export"])  # float16 weights, loaded into a float32 model
    assert exported.info["licence"] == "test" and exported.info["trained_steps"] == 400
    assert Path(summary["export"]).stat().st_size < 0.6 * (tmp_path / "run" / MODEL_FILE).stat().st_size
    assert exported.weights.keys() == bundle.weights.keys() and exported.has_graphs and bundle.has_graphs
    for name, value in bundle.weights.items():
        np.testing.assert_allclose(exported.weights[name].astype(np.float32), value, rtol=1e-3, atol=1e-4)
    g = bundle.layout.gesture_dim
    clip = read_gesture(root / "talk.bvh", 15.0)
    later = read_gesture(DATA / "beat" / "2_scott_0_1_1.bvh", 15.0, source_fps=15.0)[200:216]

    def distance(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.abs((a - b) / bundle.std[:g]).mean())

    for seed in (0, 1):
        motion = generate(str(root / "talk.wav"), model=bundle, seed=seed, device="cpu")
        sample = layout_array(motion, bundle.layout)[:, :g]
        assert len(sample) == len(clip) == 16
        # a sample from noise lands on the training clip: far closer to it than the mean pose
        # is (about 4x with the abar-weighted x0 terms; about 1.2x with unweighted ones)
        assert distance(sample, clip) < 0.35 * distance(bundle.mean[:g], clip)
        assert distance(sample, clip) < 0.5 * distance(sample, later)
    # the freshly trained model gives the same motion on both backends
    on_torch = generate(str(root / "talk.wav"), model=bundle, seed=1, backend="torch", device="cpu")
    assert motion.meta["backend"] == "onnx"
    assert np.abs(on_torch.rotations - motion.rotations).max() <= 1e-3
    assert np.abs(on_torch.face - motion.face).max() <= 1e-3


def test_training_with_hubert_features(small_root, tmp_path, tiny_hubert):
    from diffsheg_core.speech_features import hubert_encoding
    from diffsheg_core.training.data import load_takes

    model = {**TINY, "speech_encoder": "hubert", "speech_dim": 32, "speech_latent": 16}
    cfg = TrainConfig.from_dict(config(small_root, tmp_path / "run", steps=3, checkpoint_every=3,
                                       model=model, hubert=str(tiny_hubert)))
    cfg.data.cache_dir = str(tmp_path / "cache")
    assert train(cfg)["step"] == 3
    bundle = load_model(tmp_path / "run" / MODEL_FILE)
    assert bundle.config.has_speech_input and bundle.config.speech_encoder == "hubert"
    takes = load_takes(cfg.data, "train", hubert_encoding(str(tiny_hubert)))
    assert takes.takes[0].extra.shape == (takes.takes[0].n_frames, 32)  # cached with the take
    motion = generate(str(small_root / "talk.wav"), model=bundle, hubert_path=str(tiny_hubert),
                      steps=3, device="cpu")
    assert motion.n_frames == 45 and np.isfinite(motion.rotations).all()


def tiny_phonetic_encoder(path: Path) -> torch.nn.Module:
    """A small random phonetic encoder (seed 0), saved to `path` for the training settings."""
    from diffsheg_core.torch_layer.model import PhoneticEncoder
    from diffsheg_core.phonetic import PhoneticConfig
    from diffsheg_core.training.train_phonetic import save_phonetic

    torch.manual_seed(0)
    encoder = PhoneticEncoder(PhoneticConfig(channels=16, dilations=(1,))).eval()
    save_phonetic(encoder, path, {})
    return encoder


def test_training_with_the_phonetic_encoder_bundles_it(small_root, tmp_path):
    from diffsheg_core.speech_features import speech_features
    from diffsheg_core.runtime.backends import open_network
    from diffsheg_core.training.train_phonetic import speech_encoding

    encoder = tiny_phonetic_encoder(tmp_path / "phonetic.safetensors")
    # the settings names from before the second speech input was renamed still read
    model = {**TINY, "use_hubert": True, "speech_encoder": "phonetic", "hubert_latent": 16}
    settings = config(small_root, tmp_path / "run", steps=3, checkpoint_every=3, model=model,
                      phonetic=str(tmp_path / "phonetic.safetensors"),
                      export=str(tmp_path / "export.safetensors"), export_dtype="float16")
    first = train(TrainConfig.from_dict(settings))
    exported = load_model(first["export"])
    assert exported.config.speech_dim == encoder.cfg.dim and exported.config.speech_latent == 16
    assert exported.phonetic is not None and exported.has_graphs
    audio = str(small_root / "talk.wav")
    from diffsheg_core.audio import load_audio

    speech = load_audio(audio)
    trained = speech_encoding(encoder).encode(speech, 45)  # float16 export: close, not equal
    for backend in ("onnx", "torch"):
        features = speech_features(exported, open_network(exported, backend), speech)
        np.testing.assert_allclose(features.speech, trained, atol=2e-3)
    assert generate(audio, model=exported, steps=3, device="cpu").n_frames == 45

    again = train(TrainConfig.from_dict(settings))  # at the final step: only exports again
    record = json.loads((tmp_path / "run" / SUMMARY_FILE).read_text())
    assert again["step"] == 3 and record["final_loss"] == first["final_loss"] is not None
    with pytest.raises(DiffshegError, match="needs the encoder file"):
        train(TrainConfig.from_dict({**settings, "phonetic": "", "out_dir": str(tmp_path / "other")}))


def test_fine_tuning_an_unguided_run_into_a_guided_model_with_torchrun(small_root, tmp_path):
    """init_from starts from another run's weights (the null condition starts fresh), and two
    processes train the null condition even when one of them draws no dropped rows."""
    base = tmp_path / "base"
    train(TrainConfig.from_dict(config(small_root, base, steps=5, checkpoint_every=5)))
    guided_model = {**TINY, "classifier_free": True}
    settings = config(small_root, tmp_path / "guided", steps=6, checkpoint_every=100, cond_drop=0.3,
                      guidance=1.5, skip_guidance=0.2, init_from=str(base / MODEL_FILE), model=guided_model)

    start = Trainer(TrainConfig.from_dict(settings), Dist())
    assert start.source is not None and not start.begin()
    assert start.source is None  # the source model is not held for the rest of the run
    source = load_model(base / MODEL_FILE).weights
    for name, value in start.ema.state_dict().items():
        if "null_cond_emb" not in name:
            torch.testing.assert_close(value, torch.from_numpy(source[name]), msg=name)

    (tmp_path / "guided.json").write_text(json.dumps(settings))
    proc = _run(["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                 "-m", "diffsheg_core.training.train", "--config", str(tmp_path / "guided.json"), "--device", "cpu"])
    out = proc.communicate(timeout=300)[0]
    assert proc.returncode == 0, out
    first, second = json.loads((tmp_path / "guided" / SUMMARY_FILE).read_text())["param_checksums"]
    assert first == second
    bundle = load_model(tmp_path / "guided" / MODEL_FILE)
    assert bundle.config.classifier_free and bundle.guidance == 1.5 and bundle.skip_guidance == 0.2
    # the export carries the gesture prior of the training motion, and generation uses it
    assert (bundle.prior.dims, bundle.prior.max_len) == (bundle.config.gesture_dim, bundle.config.clip_len)
    motion = generate(str(small_root / "talk.wav"), model=bundle, steps=2, device="cpu")
    assert motion.meta["guidance"] == 1.5 and motion.meta["prior_start"] and np.isfinite(motion.rotations).all()

    with pytest.raises(DiffshegError, match="its model differs in latent"):
        Trainer(TrainConfig.from_dict({**settings, "model": {**guided_model, "latent": 48},
                                       "out_dir": str(tmp_path / "other")}), Dist()).begin()
    with pytest.raises(DiffshegError, match="guidance needs a model with a null condition"):
        Trainer(TrainConfig.from_dict({**settings, "model": dict(TINY), "init_from": ""}), Dist())
    with pytest.raises(DiffshegError, match="needs cond_drop above 0"):
        Trainer(TrainConfig.from_dict({**settings, "cond_drop": 0.0}), Dist())
    with pytest.raises(DiffshegError, match=r"gesture energy\) must be a number from 0 to 1"):
        Trainer(TrainConfig.from_dict({**settings, "skip_guidance": 2.0}), Dist())

    (base / MODEL_FILE).rename(base / "moved.safetensors")  # a finished run no longer needs its start
    assert train(TrainConfig.from_dict(settings))["step"] == 6


def test_speech_dropout_keeps_the_style_of_guided_models(small_root, tmp_path):
    """Guided sampling runs its null pass with the real style, so the rows trained on the
    null condition keep theirs; without a null condition the dropout drops the style."""
    seen = {}

    class Recording(UniEG):
        def forward(self, *args, **kwargs):
            seen["style"], seen["null_rows"] = args[4].clone(), kwargs.get("null_rows", 0)
            return super().forward(*args, **kwargs)

    cfg = TrainConfig.from_dict(config(small_root, tmp_path / "x", cond_drop=1.0,
                                       model={**TINY, "classifier_free": True}))
    trainer = Trainer(cfg, Dist())
    batch = trainer.batch(trainer.train_set, torch.arange(4))
    for null_condition, style_sum, null_rows in ((True, 4.0, 4), (False, 0.0, 0)):
        model = Recording(replace(trainer.model_cfg, classifier_free=null_condition))
        diffsheg_loss(model, trainer.schedule, batch, cfg, torch.Generator().manual_seed(0),
                      trainer.model_cfg.style_dim, null_condition)
        assert float(seen["style"].sum()) == style_sum and seen["null_rows"] == null_rows


def test_a_configuration_extends_its_base_table_by_table(tmp_path):
    (tmp_path / "base.toml").write_text('steps = 8000\nlr = 7e-4\nexport = "w.safetensors"\n'
                                        '[data]\nkind = "corpus"\nroot = "c"\n[model]\nlatent = 192\nlayers = 3\n')
    (tmp_path / "tune").mkdir()
    (tmp_path / "tune" / "guided.toml").write_text('extends = "../base.toml"\nsteps = 2000\ncond_drop = 0.15\n'
                                                   '[model]\nclassifier_free = true\n')
    cfg = TrainConfig.from_dict(read_config_file(tmp_path / "tune" / "guided.toml"))
    assert (cfg.steps, cfg.lr, cfg.cond_drop, cfg.export) == (2000, 7e-4, 0.15, "w.safetensors")
    assert cfg.model == {"latent": 192, "layers": 3, "classifier_free": True} and cfg.data.root == "c"
    (tmp_path / "base.toml").write_text('extends = "tune/guided.toml"\n')
    with pytest.raises(DiffshegError, match="extends it back"):
        read_config_file(tmp_path / "tune" / "guided.toml")
    (tmp_path / "odd.toml").write_text("extends = 3\n")
    with pytest.raises(DiffshegError, match="extends must be a file name"):
        read_config_file(tmp_path / "odd.toml")


def test_named_styles_a_null_style_and_the_acceleration_term(small_root, tmp_path):
    """style_drop trains that share of clips on the all-zero style; lambda_a adds the x0
    acceleration loss; the style names, the default style and the null style reach the
    model file; a default style that is not one of the names is refused."""
    seen = {}

    class Recording(UniEG):
        def forward(self, *args, **kwargs):
            seen["style"] = args[4].clone()
            return super().forward(*args, **kwargs)

    settings = config(small_root, tmp_path / "x", style_drop=0.999, style_names=["plain", "lively"],
                      default_style="lively", lambda_a=1.0)
    cfg = TrainConfig.from_dict(settings)
    trainer = Trainer(cfg, Dist())
    batch = trainer.batch(trainer.train_set, torch.arange(4))
    losses = diffsheg_loss(Recording(trainer.model_cfg), trainer.schedule, batch, cfg,
                           torch.Generator().manual_seed(0), trainer.model_cfg.style_dim, False)
    assert float(seen["style"].abs().sum()) == 0.0 and float(losses["loss_a"]) > 0
    bundle = trainer.bundle()
    assert bundle.style_names == ["plain", "lively"] and bundle.default_style == "lively" and bundle.null_style
    with pytest.raises(DiffshegError, match="default_style 'calm' is not one of the styles"):
        Trainer(TrainConfig.from_dict({**settings, "default_style": "calm", "out_dir": str(tmp_path / "y")}), Dist())
    with pytest.raises(DiffshegError, match="style_names must be 2 different names"):
        Trainer(TrainConfig.from_dict({**settings, "style_names": ["a"], "out_dir": str(tmp_path / "z")}), Dist())


def test_fine_tuning_adds_temporal_convolutions_to_the_gestures_and_keeps_the_face(small_root, tmp_path):
    """init_from a model without temporal convolutions: the new blocks (gesture branch only)
    start as the identity (the same motion from the same seed) and training moves them; with
    trains = "gestures" the expression branch and the speech layer keep the source's weights
    to the bit, so the face is the source's; the file records the kernel; a model that already
    has convolutions must match them."""
    tiny_phonetic_encoder(tmp_path / "phonetic.safetensors")  # its batch norm must keep its statistics too
    model = {**TINY, "speech_encoder": "phonetic", "speech_latent": 16}
    speech = {"phonetic": str(tmp_path / "phonetic.safetensors")}
    base = tmp_path / "base"
    train(TrainConfig.from_dict(config(small_root, base, steps=5, checkpoint_every=5, model=model, **speech)))
    settings = config(small_root, tmp_path / "conv", steps=8, checkpoint_every=100, trains="gestures",
                      init_from=str(base / MODEL_FILE), model={**model, "temporal_kernel": 5}, **speech)
    start = Trainer(TrainConfig.from_dict(settings), Dist())
    assert not start.begin()
    source = load_model(base / MODEL_FILE)
    audio = str(small_root / "talk.wav")
    before = generate(audio, model=source, steps=3, device="cpu", seed=1)
    same = generate(audio, model=start.bundle(), steps=3, device="cpu", seed=1)
    np.testing.assert_allclose(same.rotations, before.rotations, atol=1e-5)
    # the run trains in the source's normalisation, which the data's need only be close to
    np.testing.assert_array_equal(start.stats.mean, source.mean)

    train(TrainConfig.from_dict(settings))
    tuned = load_model(tmp_path / "conv" / MODEL_FILE)
    assert tuned.config.temporal_kernel == 5
    convs = [k for k in tuned.weights if "conv_block" in k]
    assert convs and all(k.startswith("encoder_ges.") for k in convs)
    assert np.abs(tuned.weights["encoder_ges.temporal_decoder_blocks.0.conv_block.proj_out.weight"]).max() > 0
    kept = [k for k in source.weights if not k.startswith("encoder_ges.")]
    assert "encoder_exp.hubert_encoder.1.running_mean" in kept
    assert kept and all(np.array_equal(tuned.weights[k], source.weights[k]) for k in kept)
    assert not all(np.array_equal(tuned.weights[k], v) for k, v in source.weights.items())
    after = generate(audio, model=tuned, steps=3, device="cpu", seed=1)
    np.testing.assert_array_equal(after.face, before.face)
    assert not np.allclose(after.rotations, before.rotations)

    with pytest.raises(DiffshegError, match="its model differs in temporal_kernel"):
        Trainer(TrainConfig.from_dict({**settings, "init_from": str(tmp_path / "conv" / MODEL_FILE),
                                       "model": {**model, "temporal_kernel": 3},
                                       "out_dir": str(tmp_path / "other")}), Dist()).begin()
    for bad in (4, -3, 5.0, True):
        with pytest.raises(DiffshegError, match=rf"temporal_kernel must be 0 \(none\) or an odd number of frames, got {bad}"):
            Trainer(TrainConfig.from_dict({**settings, "model": {**model, "temporal_kernel": bad}}), Dist())


def test_a_fine_tuned_run_keeps_its_source_normalisation_on_a_rebuilt_corpus():
    """A rebuild of the same corpus moves the statistics by a few percent of a channel's
    spread: the source's are kept. Other data is refused."""
    source = NormStats(np.array([0.2, -0.1, 0.0], np.float32), np.array([0.04, 0.5, 1.0], np.float32))
    rebuilt = NormStats(source.mean + 0.02 * source.std, source.std * 1.02)
    assert fine_tuning_statistics("v7.safetensors", source, rebuilt) is source
    other = NormStats(source.mean + np.array([0.0, 0.0, 0.2], np.float32), source.std)
    with pytest.raises(DiffshegError, match=r"init_from v7.safetensors: it was trained with other normalisation "
                       r"statistics \(up to 0.20 of a channel's spread away, the limit is 0.05\).*raise stats_tolerance"):
        fine_tuning_statistics("v7.safetensors", source, other)
    # data widened on purpose (other languages) passes a raised tolerance, in the source's normalisation
    assert fine_tuning_statistics("v7.safetensors", source, other, tolerance=0.3) is source


@pytest.mark.parametrize("over,expected", [
    ({"steps": -5}, "training setting steps must be a whole number >= 1, got -5"),
    ({"steps": "many"}, "training setting steps must be a whole number >= 1, got 'many'"),
    ({"batch_size": 0}, "training setting batch_size must be a whole number >= 1, got 0"),
    ({"out_dir": "FILE"}, "is a file, not a folder"),
])
def test_settings_no_run_can_use_are_refused_before_anything_is_written(small_root, tmp_path, over, expected):
    """steps = -5 exited 0 naming a checkpoint it never wrote; the others ended in tracebacks."""
    (tmp_path / "FILE").write_text("a file where the run folder should be")
    run = tmp_path / "run"
    settings = config(small_root, run, **{k: str(tmp_path / v) if k == "out_dir" else v for k, v in over.items()})
    with pytest.raises(DiffshegError, match=expected):
        train(TrainConfig.from_dict(settings))
    (tmp_path / "run.json").write_text(json.dumps(settings))
    result = subprocess.run([sys.executable, "-m", "diffsheg_core", "train", "--config", str(tmp_path / "run.json")],
                            cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and expected in result.stderr and "Traceback" not in result.stderr
    assert not run.exists() and (tmp_path / "FILE").read_text().startswith("a file")


def test_the_bundled_models_training_recipes_read():
    """Every stage's settings in diffsheg_core/weights (base, guided, temporal, acceleration, the
    multilingual retraining, the whole body, the fine-tune on a captured Mandarin face and
    Mandarin's own face) read with their `extends` chain resolved."""
    from pathlib import Path

    recipes = sorted((Path(__file__).resolve().parents[1] / "diffsheg_core" / "weights").glob("*.toml"))
    assert len(recipes) >= 5
    ids = set()
    for path in recipes:
        cfg = TrainConfig.from_dict(read_config_file(path))
        assert cfg.model_id.startswith("diffsheg-default-") and cfg.steps > 0, path
        assert cfg.data.kind == ("facegood" if path.name == "default_face_zh_own.toml" else "corpus"), path
        ids.add(cfg.model_id)
    assert len(ids) == len(recipes)
    languages = TrainConfig.from_dict(read_config_file(recipes[0].with_name("default_languages.toml")))
    assert languages.stats_tolerance == 0.3 and languages.trains == "all" and languages.data.root.endswith("v5")
    body = TrainConfig.from_dict(read_config_file(recipes[0].with_name("default_body.toml")))
    assert body.trains == "legs" and body.data.whole_body and body.model["lower_dim"] == 30
    face = TrainConfig.from_dict(read_config_file(recipes[0].with_name("default_face_zh.toml")))
    assert face.trains == "face" and face.keep_unsaid == 1.0 and face.data.face == "source"
    assert [(d.kind, d.pause, d.whole_body, d.face) for d in face.datasets] == [
        ("facegood", 0.0, True, "data"), ("facegood", 0.1, True, "data")]
    # Mandarin's own face (issue 42): v10's face on the capture alone, as read and joined, no English
    own = TrainConfig.from_dict(read_config_file(recipes[0].with_name("default_face_zh_own.toml")))
    assert own.trains == "face" and own.keep_unsaid == 1.0 and own.init_from.endswith("weights/default.safetensors")
    assert [(d.kind, d.pause) for d in (own.data, *own.datasets)] == [("facegood", 0.0), ("facegood", 0.1)]


def test_the_face_alone_fine_tunes_on_captured_faces_beside_the_data(small_root, tmp_path):
    """trains = "face" with the FACEGOOD takes (real Mandarin, a captured face and no body) as a
    [[datasets]] table beside [data]: the run reads both, and only the expression branch
    trains; the speech layer both branches read, the gesture branch and the gesture prior stay
    the source's to the bit. A part no network has, the face without a model to keep, and a
    dataset that sets its own clip length are refused."""
    base = tmp_path / "base"
    train(TrainConfig.from_dict(config(small_root, base, steps=5, checkpoint_every=5)))
    facegood = {"kind": "facegood", "root": str(DATA / "lang_capture" / "zh_facegood"), "stride": 34, "pause": 0.1}
    settings = config(small_root, tmp_path / "face", steps=4, checkpoint_every=100, trains="face",
                      init_from=str(base / MODEL_FILE), stats_tolerance=100.0, datasets=[facegood])
    trainer = Trainer(TrainConfig.from_dict(settings), Dist())
    names = [t.name for t in trainer.train_set.takes]
    assert names[0] == "talk" and len(names) == 5  # the recording, and four FACEGOOD takes (one held out)
    train(TrainConfig.from_dict(settings))
    source, tuned = load_model(base / MODEL_FILE), load_model(tmp_path / "face" / MODEL_FILE)
    changed = {k for k, v in source.weights.items() if not np.array_equal(tuned.weights[k], v)}
    assert changed and all(k.startswith("encoder_exp.") for k in changed)
    np.testing.assert_array_equal(tuned.prior.axes, source.prior.axes)
    for over, match in (({"trains": "body"}, "trains must be one of all, gestures, legs, face"),
                        ({"init_from": ""}, "set init_from to that model")):
        with pytest.raises(DiffshegError, match=match):
            Trainer(TrainConfig.from_dict({**settings, **over}), Dist())
    with pytest.raises(DiffshegError, match="sets clip_len apart from"):
        TrainConfig.from_dict({**settings, "datasets": [{**facegood, "clip_len": 20}]})


def test_keep_unsaid_holds_the_face_channels_a_capture_leaves_out(small_root, tmp_path):
    """keep_unsaid (issue 42): a FACEGOOD take trains only the jaw and the lips' rounding, and
    with it the face channels the capture leaves out (blinks, brows) learn the source's own
    prediction. Fine-tuned hard beside the data, they stay nearer the source than without it;
    the term is logged; a resumed run keeps the source it started from; it needs init_from."""
    base = tmp_path / "base"
    train(TrainConfig.from_dict(config(small_root, base, steps=5, checkpoint_every=5)))
    facegood = {"kind": "facegood", "root": str(DATA / "lang_capture" / "zh_facegood"), "stride": 34, "pause": 0.1}

    def settings(keep: float, steps: int = 12) -> dict:
        return config(small_root, tmp_path / f"keep{keep:g}", steps=steps, checkpoint_every=6, trains="face",
                      lr=3e-3, init_from=str(base / MODEL_FILE), stats_tolerance=100.0, datasets=[facegood],
                      keep_unsaid=keep)

    for keep in (0.0, 10.0):
        train(TrainConfig.from_dict(settings(keep)))
    unsaid = [r["loss_unsaid"] for r in read_log(tmp_path / "keep10") if "loss_unsaid" in r]
    assert unsaid[0] == 0.0 and max(unsaid) > 0  # the model starts as its source, then drifts
    assert not any("loss_unsaid" in r for r in read_log(tmp_path / "keep0"))
    trained = {}
    for keep in (0.0, 10.0):  # each run's model, resumed from its folder
        trainer = Trainer(TrainConfig.from_dict(settings(keep, steps=13)), Dist())
        assert trainer.begin()
        trained[keep] = trainer
    source = trained[10.0].unsaid_source  # read again from init_from on resuming
    for name, value in load_model(base / MODEL_FILE).weights.items():
        np.testing.assert_array_equal(source.state_dict()[name].numpy(), np.asarray(value, np.float32), err_msg=name)
    t = trained[0.0]
    clips = [i for i in range(len(t.train_set)) if not bool(t.train_set[i]["mask"].all())]  # the FACEGOOD clips
    batch = t.batch(t.train_set, torch.tensor(clips[:8]))
    drift = {}
    with torch.no_grad():
        for keep, trainer in trained.items():
            trainer.model.eval()
            losses = diffsheg_loss(trainer.model, Schedule.linear(), batch, trainer.cfg, torch.Generator().manual_seed(3),
                                   trainer.model_cfg.style_dim, False, source, trainer.model_cfg.gesture_dim)
            drift[keep] = float(losses["loss_unsaid"])
    assert drift[10.0] < 0.5 * drift[0.0], drift
    with pytest.raises(DiffshegError, match="keep_unsaid keeps what the data leaves out"):
        Trainer(TrainConfig.from_dict({**settings(1.0), "init_from": "", "trains": "all"}), Dist())
    # face = "source": a dataset rehearsed with its face left to the source (keep_unsaid teaches it)
    faced = tmp_path / "faced"
    write_take(faced, "talk", 12.0, 3.0, face=True)
    rehearsed = settings(1.0)
    rehearsed["data"] = {**rehearsed["data"], "face": "source", "root": str(faced), "cache_dir": str(faced / "cache")}
    rehearsed["datasets"] = [{**facegood, "face": "data"}]
    t = Trainer(TrainConfig.from_dict({**rehearsed, "out_dir": str(tmp_path / "rehearsed")}), Dist())
    g = t.model_cfg.gesture_dim
    talk, captured = t.train_set.takes[0], t.train_set.takes[1]
    assert talk.taught[:g].all() and not talk.taught[g:].any()  # its body still trains
    held = talk.mask[g:]  # the face channels the recording holds, still in its clips as recorded
    assert held.any()
    item = t.train_set[next(i for i, (take, _) in enumerate(t.train_set.index) if take == 0)]
    assert np.array_equal(item["mask"].numpy(), talk.taught.astype(np.float32))
    assert item["motion"][:, g:][:, torch.from_numpy(held)].abs().sum() > 0
    assert captured.taught is None and captured.mask[g:].any() and not captured.mask[:g].any()
    with pytest.raises(DiffshegError, match=r"takes its face from the source model \(face = \"source\"\): set keep_unsaid"):
        Trainer(TrainConfig.from_dict({**rehearsed, "keep_unsaid": 0.0}), Dist())
    with pytest.raises(DiffshegError, match="data setting face must be"):
        Trainer(TrainConfig.from_dict({**rehearsed, "data": {**rehearsed["data"], "face": "teacher"}}), Dist())


def test_a_beat_model_widens_into_a_whole_body_one_that_keeps_its_upper_body(tmp_path):
    """init_from a `beat` model with whole_body data (layout beat_body: 30 more gesture
    channels, the hips, legs and hips' translation, made by a lower-body branch of their
    own): the widened network predicts the old channels exactly as the source does, the run
    keeps the source's normalisation for the old channels and takes the data's for the new
    ones, and with trains = "legs" only the lower-body branch trains.
    The teacher's corpus (v4) holds the legs; any other dataset is refused, and so is a
    widening without the branch."""
    from diffsheg_core.rigs import BEAT, BEAT_BODY
    from diffsheg_core.training.corpus.build import BuildConfig, build

    text = tmp_path / "one.txt"
    text.write_text("Peter and Bob bought a map of the big park before the rain.")
    build(BuildConfig(out=tmp_path / "c", hours=6 / 3600, jobs=1, seed=5, engines=("espeak",), text_files=(text,)),
          progress=False)
    data = {"kind": "corpus", "root": str(tmp_path / "c"), "clip_len": 16, "stride": 4, "val_fraction": 0.0,
            "cache_dir": str(tmp_path / "cache")}
    model = {**TINY, "style_dim": 3}
    base = tmp_path / "base"
    train(TrainConfig.from_dict(config(tmp_path, base, steps=5, checkpoint_every=5, model=model, data=data)))
    settings = config(tmp_path, tmp_path / "body", steps=6, checkpoint_every=100, trains="legs",
                      init_from=str(base / MODEL_FILE),
                      model={**model, "lower_dim": 30, "lower_layers": 1}, data={**data, "whole_body": True})
    with pytest.raises(DiffshegError, match="which a branch of their own makes: set lower_dim = 30"):
        Trainer(TrainConfig.from_dict({**settings, "model": model, "trains": "gestures"}), Dist()).begin()
    with pytest.raises(DiffshegError, match="trains the lower-body branch alone, and this model has none"):
        Trainer(TrainConfig.from_dict({**settings, "model": model}), Dist())
    start = Trainer(TrainConfig.from_dict(settings), Dist())
    assert not start.begin() and start.model_cfg.layout == "beat_body" and start.model_cfg.gesture_dim == 171
    source = load_model(base / MODEL_FILE)
    channels = BEAT_BODY.widened_channels(BEAT)
    np.testing.assert_array_equal(start.stats.mean[channels], source.mean)
    np.testing.assert_array_equal(start.stats.std[channels], source.std)

    old = UniEG(source.config).eval()
    old.load_state_dict({k: torch.from_numpy(np.array(v)).float() for k, v in source.weights.items()})
    torch.manual_seed(2)
    x = torch.randn(2, 16, BEAT_BODY.dim)
    t, mel, style = torch.tensor([900, 40]), torch.rand(2, 16, 128), torch.eye(3)[:2]
    coefs = (torch.full((2, 1, 1), 1.5), torch.full((2, 1, 1), 0.5))
    with torch.no_grad():
        wide = start.model.eval()(x, t, mel, None, style, coefs)
        narrow = old(x[..., torch.from_numpy(channels)], t, mel, None, style, coefs)
    np.testing.assert_allclose(wide[..., channels].numpy(), narrow.numpy(), atol=1e-5)

    train(TrainConfig.from_dict(settings))
    tuned = load_model(tmp_path / "body" / MODEL_FILE)
    assert tuned.layout is BEAT_BODY and tuned.prior.dims == 171
    # the upper body's windows start from the source's prior, the legs' from one fitted beside it
    np.testing.assert_array_equal(tuned.prior.axes[:BEAT.gesture_dim, :BEAT.gesture_dim], source.prior.axes)
    assert not tuned.prior.axes[:BEAT.gesture_dim, BEAT.gesture_dim:].any()
    for key, value in source.weights.items():  # the upper body and the face are the source's to the bit
        np.testing.assert_array_equal(tuned.weights[key], value)
    lower = [k for k in tuned.weights if k.startswith("encoder_low.")]
    assert lower and set(tuned.weights) == set(source.weights) | set(lower)
    assert not all(np.array_equal(start.bundle().weights[k], tuned.weights[k]) for k in lower)
    with pytest.raises(DiffshegError, match="its gesture prior covers 171 channels, but the gesture branch makes 141"):
        Trainer(TrainConfig.from_dict({**settings, "init_from": str(tmp_path / "body" / MODEL_FILE),
                                       "out_dir": str(tmp_path / "again")}), Dist())
    with pytest.raises(DiffshegError, match="whole_body needs the project's corpus"):
        Trainer(TrainConfig.from_dict(config(tmp_path, tmp_path / "x", model=model,
                                             data={"kind": "folder", "root": str(tmp_path), "whole_body": True})),
                Dist())

    # generating with it: the network's own hips and legs, planted; none with upper_body_only;
    # a regenerated range keeps the take's legs
    from diffsheg_core import lower_body as lb
    from diffsheg_core.pipeline import Pin, regenerate

    speech = DATA / "beat2" / "2_scott_0_1_1.wav"
    y, sr = sf.read(speech, dtype="float32")
    audio = (y[:4 * sr], sr)
    motion = generate(*audio, model=tuned, steps=3, device="cpu", seed=1)
    assert motion.rig == "beat" and motion.joint_names == list(BEAT_BODY.joint_names)
    assert motion.meta["lower_body"] == "model" and motion.root_translation.shape == (motion.n_frames, 3)
    soles = lb.foot_positions(motion.rotations[:, len(BEAT.joint_names):].astype(np.float64),
                              motion.root_translation.astype(np.float64))
    for side, spans in motion.meta["contacts"].items():
        for a, b in spans:
            assert np.linalg.norm(np.diff(soles[side][1][a:b + 1], axis=0), axis=-1).max() < 0.01
    upper = generate(*audio, model=tuned, steps=3, device="cpu", seed=1, upper_body_only=True)
    assert upper.joint_names == list(BEAT.joint_names) and upper.root_translation is None
    # the same seed gives the source's gestures and face: the legs are an addition
    before = generate(*audio, model=source, steps=3, device="cpu", seed=1, upper_body_only=True)
    np.testing.assert_allclose(upper.rotations, before.rotations, atol=1e-4)
    np.testing.assert_allclose(upper.face, before.face, atol=1e-4)
    again = regenerate(motion, *audio, model=tuned, start=10, end=30, steps=3, device="cpu", seed=2)
    np.testing.assert_array_equal(again.rotations[:, len(BEAT.joint_names):], motion.rotations[:, len(BEAT.joint_names):])
    np.testing.assert_array_equal(again.root_translation, motion.root_translation)
    np.testing.assert_array_equal(again.rotations[:10], motion.rotations[:10])
    assert not np.array_equal(again.rotations[10:30], motion.rotations[10:30])
    again = regenerate(upper, *audio, model=tuned, start=10, end=30, steps=3, device="cpu", seed=2)
    assert again.joint_names == list(BEAT.joint_names) and again.root_translation is None
    with pytest.raises(DiffshegError, match="the hips and legs are not pinned"):
        regenerate(motion, *audio, model=tuned, start=10, end=30, pins=(Pin(15, "LeftLeg", (0.0, 0.0, 0.0)),))


def test_a_guided_model_distils_into_a_student_that_its_file_carries(small_root, tmp_path):
    """objective = "distill" (training.distill): a copy of a guided model learns its guided fast
    steps, one pass each. The loss falls; the run's file is the teacher's, weights to the bit,
    with the student in it (its products in int8), which then makes the fast sampling. A model without guidance has
    nothing to distil, and an unknown objective is named."""
    base = tmp_path / "base"
    train(TrainConfig.from_dict(config(small_root, base, steps=5, checkpoint_every=5)))
    guided = config(small_root, tmp_path / "guided", steps=5, checkpoint_every=5, cond_drop=0.3, guidance=1.5,
                    skip_guidance=0.2, init_from=str(base / MODEL_FILE), model={**TINY, "classifier_free": True})
    train(TrainConfig.from_dict(guided))
    settings = {**guided, "out_dir": str(tmp_path / "student"), "objective": "distill", "steps": 30,
                "checkpoint_every": 100, "init_from": str(tmp_path / "guided" / MODEL_FILE)}
    train(TrainConfig.from_dict(settings))
    losses = [r["loss"] for r in read_log(tmp_path / "student") if "loss" in r]
    assert np.mean(losses[-5:]) < 0.7 * np.mean(losses[:5]), losses

    teacher, run = load_model(tmp_path / "guided" / MODEL_FILE), load_model(tmp_path / "student" / MODEL_FILE)
    assert run.guidance == 1.5 and run.skip_guidance == 0.2 and run.student is not None
    for name, value in teacher.weights.items():
        np.testing.assert_array_equal(run.weights[name], value)
    assert run.student.info["distilled"] | {"steps": 0} == {
        "from": teacher.model_id, "guidance": 1.5, "skip_guidance": 0.2, "refine_skip": 1.0,
        "timesteps": [50, 300, 450, 650, 900], "refine_offset": 1000, "steps": 0}
    motion = generate(str(small_root / "talk.wav"), model=run, device="cpu")
    assert motion.meta["student"] == run.student.model_id and np.isfinite(motion.rotations).all()
    # the student's products by weights run in int8 (torch_layer.export), the teacher's in float
    assert all(b"MatMulInteger" in run.student.graphs[g] and b"MatMulInteger" not in run.graphs[g]
               for g in ("expression", "gesture"))

    with pytest.raises(DiffshegError, match="there is nothing to distil from an unguided one"):
        Trainer(TrainConfig.from_dict({**settings, "init_from": str(base / MODEL_FILE),
                                       "out_dir": str(tmp_path / "other")}), Dist())
    with pytest.raises(DiffshegError, match="objective must be one of denoise, distill"):
        Trainer(TrainConfig.from_dict({**settings, "objective": "consistency"}), Dist())
