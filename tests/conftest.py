"""Shared fixtures and helpers: small seeded Gaussian scenes, the built-in room per size, the model
commands run in-process, a tiny SAM."""

from __future__ import annotations

# langfield first: it sets OpenMP's wait before torch loads (langfield/__init__.py).
import langfield  # noqa: F401

# isort: split
import pytest
import torch

from langfield.camera import Camera


def random_gaussians(n: int, channels: int, seed: int = 0, log_scale: float = -3.0) -> list[torch.Tensor]:
    """means, quats, scales, opacities, features of n random Gaussians around the origin."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 2
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.5 + log_scale)
    opacities = torch.rand(n, generator=g) * 0.9 + 0.05
    features = torch.rand(n, channels, generator=g)
    return [means, quats, scales, opacities, features]


@pytest.fixture
def small_camera() -> Camera:
    return Camera.look_at((0.0, -3.0, 0.5), (0.0, 0.0, 0.0), width=40, height=30, fov_x_deg=60)


@pytest.fixture(scope="session")
def room_factory(tmp_path_factory):
    """``room_factory(width, height, **kwargs)``: the built-in room (seed 0 unless given), generated once
    per session for each set of arguments. Shared between modules: copy it before changing a file."""
    from langfield.synthetic import make_room

    made = {}

    def room(width: int, height: int, **kwargs):
        key = (width, height, tuple(sorted(kwargs.items())))
        if key not in made:
            made[key] = make_room(tmp_path_factory.mktemp("room"), width=width, height=height, **kwargs)
        return made[key]

    return room


def run_models_cli(argv: list[str]) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of the export / preprocess parsers, as langfield.cli.main runs them."""
    import argparse
    import contextlib
    import io

    from langfield.cli import models as cli_models

    parser = argparse.ArgumentParser(prog="langfield")
    cli_models.add_parsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = args.func(args)
        except (FileNotFoundError, ValueError) as exc:  # what cli.main turns into one line and status 2
            print(f"langfield {args.command}: error: {exc}", file=err)
            code = 2
    return code, out.getvalue(), err.getvalue()


def tiny_sam(size: int, window_size: int, seed: int):
    """A randomly initialised SAM of the real architecture, tiny (ViT 32-d, 2 blocks, ``size`` px input);
    skips the test where segment-anything (the export extra) is missing."""
    from functools import partial

    modeling = pytest.importorskip(
        "segment_anything.modeling",
        reason="needs segment_anything.modeling from the export extra (make test-export)",
    )
    torch.manual_seed(seed)
    dim, patch = 32, 16
    return modeling.Sam(
        image_encoder=modeling.ImageEncoderViT(
            depth=2,
            embed_dim=dim,
            img_size=size,
            mlp_ratio=2,
            norm_layer=partial(torch.nn.LayerNorm, eps=1e-6),
            num_heads=2,
            patch_size=patch,
            qkv_bias=True,
            use_rel_pos=True,
            global_attn_indexes=(1,),
            window_size=window_size,
            out_chans=dim,
        ),
        prompt_encoder=modeling.PromptEncoder(
            embed_dim=dim,
            image_embedding_size=(size // patch, size // patch),
            input_image_size=(size, size),
            mask_in_chans=4,
        ),
        mask_decoder=modeling.MaskDecoder(
            num_multimask_outputs=3,
            transformer=modeling.TwoWayTransformer(depth=2, embedding_dim=dim, mlp_dim=64, num_heads=2),
            transformer_dim=dim,
            iou_head_depth=3,
            iou_head_hidden_dim=32,
        ),
        pixel_mean=[123.675, 116.28, 103.53],
        pixel_std=[58.395, 57.12, 57.375],
    ).eval()


def bare_room(path, width: int, height: int, seed: int = 0, n_test: int = 2):
    """The built-in room at ``path`` without what preprocessing writes: no language features, no depth
    priors, no ``depth_kind``."""
    import json
    import shutil

    from langfield.synthetic import make_room

    root = make_room(path, seed=seed, width=width, height=height, n_test=n_test)
    shutil.rmtree(root / "language_features")
    shutil.rmtree(root / "depths")
    meta = json.loads((root / "transforms.json").read_text())
    del meta["depth_kind"]
    (root / "transforms.json").write_text(json.dumps(meta))
    return root
