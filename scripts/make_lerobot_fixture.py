#!/usr/bin/env python3
"""Reference fixture from LeRobot's real DiffusionPolicy (tiny config), for the tch port.

    VENV=$(bash scripts/lerobot_venv.sh)
    "$VENV/bin/python" scripts/make_lerobot_fixture.py [--out policies/tests/fixtures/lerobot_dp_tiny]

Writes (layout documented in the fixture's README.md):
  weights.safetensors.gz  every replaced state_dict entry K as uint8 codes K (shape of K) plus
                          float32 scalars K.scale, K.offset; value = offset + scale * (codes - 1)
  lerobot/                LeRobot's own save: config.json + pre/post-processor json + stats
                          safetensors (model.safetensors deleted: rebuild it from the above)
  io.safetensors          inputs, noise, intermediates and outputs, batch 2
Deterministic: a second run writes byte-identical files (checked with --check-determinism).
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import json
import math
import shutil
import sys
from pathlib import Path

import torch
from torch import nn

torch.set_num_threads(1)  # bit-for-bit reproducible CPU kernels

import diffusers  # noqa: E402
import lerobot  # noqa: E402
from safetensors.torch import save, save_file  # noqa: E402

from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature  # noqa: E402
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig  # noqa: E402
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy  # noqa: E402
from lerobot.policies.diffusion.processor_diffusion import make_diffusion_pre_post_processors  # noqa: E402
from lerobot.policies.utils import populate_queues  # noqa: E402
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "policies/tests/fixtures/lerobot_dp_tiny"

CAMS = ["observation.images.ext1", "observation.images.ext2"]
B, TO, HORIZON, N_ACT, D = 2, 2, 16, 8, 7
IMG = (3, 64, 64)
SEED = 20240611

# ------------------------------------------------------------------ normaliser stats
# Images: MEAN_STD with (3, 1, 1) stats, as LeRobot datasets store them.
IMG_STATS = {
    "observation.images.ext1": {  # ImageNet
        "mean": [0.485, 0.456, 0.406],
        "std": [0.229, 0.224, 0.225],
    },
    "observation.images.ext2": {  # something else
        "mean": [0.52, 0.47, 0.39],
        "std": [0.27, 0.25, 0.29],
    },
}
# State / action: x, y, z [m], three rotation components in [-1, 1], gripper.
STATE_MIN = [0.30, -0.25, 0.05, -1.0, -1.0, -0.60, 0.00]
STATE_MAX = [0.70, 0.25, 0.55, 1.0, 1.0, 0.60, 0.08]
ACTION_MIN = [0.32, -0.22, 0.08, -1.0, -0.90, 0.25, 0.00]
ACTION_MAX = [0.68, 0.24, 0.50, 1.0, 0.90, 0.25, 1.00]  # dim 5: min == max (zero range)
ZERO_RANGE_ACTION_DIM = 5


def make_stats() -> dict[str, dict[str, torch.Tensor]]:
    stats: dict[str, dict[str, torch.Tensor]] = {}
    for cam, s in IMG_STATS.items():
        stats[cam] = {
            "mean": torch.tensor(s["mean"], dtype=torch.float32).view(3, 1, 1),
            "std": torch.tensor(s["std"], dtype=torch.float32).view(3, 1, 1),
            "min": torch.zeros(3, 1, 1),
            "max": torch.ones(3, 1, 1),
        }
    for key, lo, hi in ((OBS_STATE, STATE_MIN, STATE_MAX), (ACTION, ACTION_MIN, ACTION_MAX)):
        lo_t = torch.tensor(lo, dtype=torch.float32)
        hi_t = torch.tensor(hi, dtype=torch.float32)
        stats[key] = {
            "min": lo_t,
            "max": hi_t,
            "mean": (lo_t + hi_t) / 2,
            "std": (hi_t - lo_t) / 4,
        }
    return stats


def make_config() -> DiffusionConfig:
    return DiffusionConfig(
        device="cpu",
        push_to_hub=False,
        input_features={
            CAMS[0]: PolicyFeature(type=FeatureType.VISUAL, shape=IMG),
            CAMS[1]: PolicyFeature(type=FeatureType.VISUAL, shape=IMG),
            OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(D,)),
        },
        output_features={ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(D,))},
        normalization_mapping={
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MIN_MAX,
            "ACTION": NormalizationMode.MIN_MAX,
        },
        n_obs_steps=TO,
        horizon=HORIZON,
        n_action_steps=N_ACT,
        vision_backbone="resnet18",
        pretrained_backbone_weights=None,
        use_group_norm=True,
        spatial_softmax_num_keypoints=8,
        crop_shape=(56, 56),
        crop_is_random=True,
        use_separate_rgb_encoder_per_camera=True,
        down_dims=(32, 64),
        kernel_size=5,
        n_groups=8,
        diffusion_step_embed_dim=32,
        use_film_scale_modulation=True,
        noise_scheduler_type="DDIM",
        num_train_timesteps=100,
        beta_schedule="squaredcos_cap_v2",
        clip_sample=True,
        clip_sample_range=1.0,
        prediction_type="epsilon",
        num_inference_steps=16,
    )


# ------------------------------------------------------------------ weight encoding
TERNARY_STD = math.sqrt(0.2)  # std of (code - 1) with P(0) = P(2) = 0.1, P(1) = 0.8


def weight_rule(key: str, tensor: torch.Tensor, module: nn.Module) -> tuple[float, float, str]:
    """(offset, scale, rule name) for one state_dict entry."""
    leaf = key.rsplit(".", 1)[1]
    if leaf == "bias":
        return 0.0, 0.02, "bias"
    if isinstance(module, nn.GroupNorm) and leaf == "weight":
        return 1.0, 0.1, "groupnorm.weight"
    if leaf == "weight" and tensor.dim() >= 2:
        fan_in, _ = nn.init._calculate_fan_in_and_fan_out(tensor)
        # kaiming_uniform_(a=0) std = gain / sqrt(fan_in) = sqrt(2 / fan_in)
        return 0.0, math.sqrt(2.0 / fan_in) / TERNARY_STD, "kaiming(fan_in=%d)" % fan_in
    raise ValueError(f"no rule for {key} {tuple(tensor.shape)} {type(module).__name__}")


def encode_weights(policy: DiffusionPolicy):
    """Replace all parameters (not pos_grid) by ternary-coded values.

    Returns (encoded dict for safetensors, reconstructed state_dict, excluded keys, rules)."""
    modules = dict(policy.named_modules())
    sd = policy.state_dict()
    gen = torch.Generator().manual_seed(SEED)
    encoded: dict[str, torch.Tensor] = {}
    recon: dict[str, torch.Tensor] = {}
    excluded: list[str] = []
    rules: dict[str, str] = {}
    for key, value in sd.items():
        if key.endswith("pos_grid"):
            excluded.append(key)
            recon[key] = value.clone()
            continue
        assert value.dtype == torch.float32, (key, value.dtype)
        module = modules[key.rsplit(".", 1)[0]]
        offset, scale, rule = weight_rule(key, value, module)
        u = torch.rand(value.shape, generator=gen, dtype=torch.float32)
        codes = torch.ones(value.shape, dtype=torch.uint8)
        codes[u < 0.1] = 0
        codes[u >= 0.9] = 2
        off_t = torch.tensor(offset, dtype=torch.float32)
        scale_t = torch.tensor(scale, dtype=torch.float32)
        # exactly: offset + scale * (code - 1), two separate float32 elementwise ops
        recon[key] = off_t + scale_t * (codes.to(torch.float32) - 1.0)
        encoded[key] = codes.contiguous()
        encoded[key + ".scale"] = scale_t
        encoded[key + ".offset"] = off_t
        rules[key] = rule
    return encoded, recon, excluded, rules


# ------------------------------------------------------------------ inputs
def smooth_images(gen: torch.Generator) -> torch.Tensor:
    """(B, To, 3, 64, 64) in [0, 1]: bilinear-upsampled 4x4 + 8x8 noise plus a soft blob."""
    n = B * TO
    coarse = torch.rand((n, 3, 4, 4), generator=gen)
    mid = torch.rand((n, 3, 8, 8), generator=gen)
    img = 0.65 * nn.functional.interpolate(coarse, size=IMG[1:], mode="bilinear", align_corners=False)
    img = img + 0.25 * nn.functional.interpolate(mid, size=IMG[1:], mode="bilinear", align_corners=False)
    ys = torch.linspace(-1.0, 1.0, IMG[1]).view(1, 1, -1, 1)
    xs = torch.linspace(-1.0, 1.0, IMG[2]).view(1, 1, 1, -1)
    centre = torch.rand((n, 1, 2, 1), generator=gen) * 1.2 - 0.6
    cy = centre[:, :, 0:1, :]
    cx = centre[:, :, 1:2, :]
    blob = torch.exp(-((ys - cy) ** 2 + (xs - cx) ** 2) / 0.08)
    colour = torch.rand((n, 3, 1, 1), generator=gen)
    img = img + 0.35 * blob * (colour - 0.5)
    return img.clamp(0.0, 1.0).view(B, TO, *IMG).contiguous()


def make_inputs() -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(SEED + 1)
    out = {cam: smooth_images(gen) for cam in CAMS}
    lo = torch.tensor(STATE_MIN)
    hi = torch.tensor(STATE_MAX)
    u = 0.05 + 0.9 * torch.rand((B, TO, D), generator=gen)
    out[OBS_STATE] = (lo + (hi - lo) * u).contiguous()
    out["noise"] = torch.randn((B, HORIZON, D), generator=gen).contiguous()
    return out


# ------------------------------------------------------------------ main
def build(out_dir: Path) -> dict:
    torch.manual_seed(SEED)
    config = make_config()
    stats = make_stats()
    policy = DiffusionPolicy(config)
    policy.eval()

    encoded, recon, excluded, rules = encode_weights(policy)
    missing, unexpected = policy.load_state_dict(recon, strict=True)
    assert not missing and not unexpected
    after = policy.state_dict()
    assert list(after) == list(recon)
    for k, v in after.items():
        assert v.dtype == recon[k].dtype and torch.equal(v, recon[k]), k
    policy.eval()

    preprocessor, postprocessor = make_diffusion_pre_post_processors(config, dataset_stats=stats)

    # ---- LeRobot's own save
    lr_dir = out_dir / "lerobot"
    if lr_dir.exists():
        shutil.rmtree(lr_dir)
    policy.save_pretrained(lr_dir)
    preprocessor.save_pretrained(lr_dir)
    postprocessor.save_pretrained(lr_dir)
    (lr_dir / "model.safetensors").unlink()

    # ---- weights
    raw = save(encoded)
    (out_dir / "weights.safetensors.gz").write_bytes(gzip.compress(raw, compresslevel=9, mtime=0))

    # ---- inputs
    inp = make_inputs()
    noise = inp["noise"]
    io: dict[str, torch.Tensor] = {k: v for k, v in inp.items()}

    with torch.inference_mode():
        # Per-step preprocessing, as at deployment (the preprocessor sees one time step).
        # (The pipeline's output dict also carries "action": None etc.; keep the observations.)
        norm_steps = [
            {k: v for k, v in preprocessor({k: inp[k][:, s].clone() for k in (*CAMS, OBS_STATE)}).items()
             if k in (*CAMS, OBS_STATE)}
            for s in range(TO)
        ]
        normalized = {k: torch.stack([ns[k] for ns in norm_steps], dim=1) for k in (*CAMS, OBS_STATE)}
        for k, v in normalized.items():
            io["normalized." + k] = v.contiguous()

        model = policy.diffusion
        # Per-camera rgb encoder output (eval: centre crop).
        for i, cam in enumerate(CAMS):
            feats = model.rgb_encoder[i](normalized[cam].flatten(0, 1))
            io["features." + cam.rsplit(".", 1)[1]] = feats.view(B, TO, -1).contiguous()

        batch = {
            OBS_STATE: normalized[OBS_STATE],
            OBS_IMAGES: torch.stack([normalized[c] for c in CAMS], dim=-4),
        }
        global_cond = model._prepare_global_conditioning(batch)
        io["global_cond"] = global_cond.contiguous()

        # Record every U-Net call of the DDIM loop.
        calls: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []

        def hook(_mod, args, kwargs, output):
            x, t = args[0], args[1]
            calls.append((x.clone(), t.clone(), output.clone()))

        handle = model.unet.register_forward_hook(hook, with_kwargs=True)
        chunk = model.conditional_sample(B, global_cond=global_cond, noise=noise.clone())
        handle.remove()
        assert len(calls) == config.num_inference_steps
        ts = [int(c[1][0]) for c in calls]
        assert all(bool((c[1] == c[1][0]).all()) for c in calls)
        assert torch.equal(calls[0][0], noise)

        io["t.first"] = torch.tensor(ts[0], dtype=torch.int64)
        io["eps.first"] = calls[0][2].contiguous()
        io["t.last"] = torch.tensor(ts[-1], dtype=torch.int64)
        io["eps.last"] = calls[-1][2].contiguous()
        io["t.all"] = torch.tensor(ts, dtype=torch.int64)
        io["eps.all"] = torch.stack([c[2] for c in calls]).contiguous()
        io["x.all"] = torch.stack([c[0] for c in calls]).contiguous()
        io["chunk.normalized"] = chunk.contiguous()
        action = postprocessor(chunk.clone())
        io["action"] = action.contiguous()

        # LeRobot's select path: queue two observation steps, then select_action x n_action_steps.
        policy.reset()
        first = dict(norm_steps[0])
        first[OBS_IMAGES] = torch.stack([first[c] for c in CAMS], dim=-4)
        populate_queues(policy._queues, first)
        executed = []
        for i in range(N_ACT):
            a = policy.select_action(dict(norm_steps[1]), noise=noise.clone() if i == 0 else None)
            executed.append(postprocessor(a))
        executed_t = torch.stack(executed, dim=1)
        io["action.executed"] = executed_t.contiguous()

        # Also the direct generate_actions path.
        gen_actions = postprocessor(model.generate_actions(batch, noise=noise.clone()))

    # Checks.
    start = TO - 1
    exec_equal = torch.equal(executed_t, action[:, start : start + N_ACT])
    gen_equal = torch.equal(gen_actions, executed_t)
    zero_dim = action[..., ZERO_RANGE_ACTION_DIM]

    sched = model.noise_scheduler
    io["scheduler.alphas_cumprod"] = sched.alphas_cumprod.to(torch.float32).contiguous()
    save_file({k: v.contiguous() for k, v in io.items()}, str(out_dir / "io.safetensors"))

    info = {
        "versions": {
            "lerobot": lerobot.__version__,
            "torch": torch.__version__,
            "diffusers": diffusers.__version__,
            "python": sys.version.split()[0],
        },
        "timesteps": ts,
        "scheduler_config": {
            k: (v if isinstance(v, (int, float, str, bool, type(None))) else str(v))
            for k, v in dict(sched.config).items()
        },
        "final_alpha_cumprod": float(sched.final_alpha_cumprod),
        "executed_equals_action_1_9": exec_equal,
        "generate_actions_equals_select_path": gen_equal,
        "max_abs_executed_minus_action_1_9": float((executed_t - action[:, start : start + N_ACT]).abs().max()),
        "zero_range_dim_values": sorted({float(x) for x in zero_dim.flatten()}),
        "excluded_keys": excluded,
        "n_state_dict_keys": len(recon),
        "n_params": sum(p.numel() for p in policy.parameters()),
        "state_dict": [[k, list(v.shape), rules.get(k, "kept")] for k, v in recon.items()],
        "eps_first_absmax": float(io["eps.first"].abs().max()),
        "chunk_absmax": float(chunk.abs().max()),
    }
    return info


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--info", type=Path, default=None, help="write a JSON summary (key list etc.) here")
    ap.add_argument("--check-determinism", action="store_true", help="build twice, compare bytes")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    info = build(args.out)
    if args.check_determinism:
        files = ["io.safetensors", "weights.safetensors.gz"]
        first = {f: digest(args.out / f) for f in files}
        build(args.out)
        second = {f: digest(args.out / f) for f in files}
        assert first == second, (first, second)
        info["determinism"] = first
        print("determinism: OK", first)
    if args.info:
        args.info.write_text(json.dumps(info, indent=1))
    print(json.dumps({k: v for k, v in info.items() if k != "state_dict"}, indent=1))
    for p in sorted(args.out.rglob("*")):
        if p.is_file():
            print(f"{p.stat().st_size:>10}  {p.relative_to(args.out)}")


if __name__ == "__main__":
    main()
