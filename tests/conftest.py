"""Shared test fixtures: paths to the real reference data beside the checkout."""

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATA = SHARED / "data"
GOLDEN = SHARED / "golden"


def pytest_configure(config):
    if not DATA.is_dir():
        raise pytest.UsageError(f"reference data not found at {DATA}: the tests need ../shared beside the checkout")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA


@pytest.fixture(scope="session")
def golden_dir() -> Path:
    return GOLDEN


@pytest.fixture(scope="session")
def tiny_hubert(tmp_path_factory) -> Path:
    """A randomly initialised HuBERT with the real layer layout but tiny widths, saved to disk."""
    transformers = pytest.importorskip("transformers")
    import torch

    torch.manual_seed(0)
    config = transformers.HubertConfig(
        hidden_size=32, num_hidden_layers=2, num_attention_heads=2, intermediate_size=64,
        conv_dim=(16,) * 7, num_conv_pos_embeddings=16, num_conv_pos_embedding_groups=2)
    folder = tmp_path_factory.mktemp("tiny_hubert")
    transformers.HubertModel(config).save_pretrained(folder)
    return folder


def blas_threads() -> frozenset[int]:
    """The threads numpy's BLAS libraries run on now (threadpoolctl; empty where numpy has none)."""
    from threadpoolctl import threadpool_info

    return frozenset(info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas")


def random_bundle(graphs: bool = True, seed: int = 0, **config):
    """A small randomly initialised model (no learned motion) as a ModelBundle, with its
    ONNX graphs unless `graphs` is false. `config`: ModelConfig fields over a small mel-only
    BEAT network (latent 64, 2 layers)."""
    import numpy as np
    import torch

    from diffsheg_core.checkpoints import ModelBundle
    from diffsheg_core.config import ModelConfig
    from diffsheg_core.foppas import PRESETS
    from diffsheg_core.torch_layer.export import with_graphs
    from diffsheg_core.torch_layer.model import UniEG, state_arrays

    cfg = ModelConfig(**{"latent": 64, "layers": 2, "ff": 128, "heads": 4, "speech_encoder": None, **config})
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = UniEG(cfg).eval()
        for name, p in model.named_parameters():  # wake the zero-initialised layers up
            if p.abs().max() == 0:
                torch.nn.init.normal_(p, std=0.02)
    bundle = ModelBundle(config=cfg, weights=state_arrays(model),
                         mean=np.zeros(cfg.dim, np.float32), std=np.full(cfg.dim, 0.05, np.float32),
                         sampling=PRESETS["official-beat"], model_id="random-small", trained=False,
                         source="random-small")
    return with_graphs(bundle) if graphs else bundle
