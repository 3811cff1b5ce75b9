"""Makes tests/fixtures/policies/torchscript_tiny: a small pixels-and-proprioception policy
written in PyTorch and exported by PyTorch itself, with torch.jit.script and torch.jit.trace, in
the signature `labrig policy run --torchscript` documents (ARCHITECTURE.md):

    forward(obs: Dict[str, Tensor]) -> Tensor
      obs["observation.images.<camera>"]: (B, To, 3, S, S) float32 RGB in [0, 1]
      obs["observation.state"]:           (B, To, 8) float32: TCP xyz (m), its quaternion
                                          x y z w (w >= 0, labrig's top-down hemisphere), the
                                          gripper's opening (0 open .. 1 closed)
      returns                             (B, Tp, 7) float32 actions in the robot's units, row
                                          To - 1 for the newest observation's tick

Its action space is DROID's cartesian_velocity: 6 velocities in [-0.2, 0.2] (tanh x 0.2, so an
untrained net moves the arm slowly) and the gripper in [0, 1] (sigmoid). Weights are seeded:
the same script gives the same files. Also writes spec.toml and expected.json: inputs by a
formula both sides compute (no binary inputs to commit) and PyTorch's outputs for them, eager,
scripted and traced.

Needs a full `pip install torch==2.13.0` (FACTS.md: 2.7 GB; not part of setup):
    python scripts/make_torchscript_fixture.py tests/fixtures/policies/torchscript_tiny
"""

import json
import sys
from pathlib import Path
from typing import Dict

import torch
from torch import Tensor, nn

CAMERAS = ["wrist", "ext1"]
SIZE, TO, TP, A, STATE = 64, 2, 16, 7, 8


class TinyPolicy(nn.Module):
    horizon: torch.jit.Final[int]
    action_dim: torch.jit.Final[int]

    def __init__(self):
        super().__init__()
        self.horizon, self.action_dim = TP, A
        self.encoders = nn.ModuleDict(
            {
                c: nn.Sequential(
                    nn.Conv2d(3, 8, 5, stride=4),
                    nn.ReLU(),
                    nn.Conv2d(8, 8, 3, stride=2),
                    nn.ReLU(),
                    nn.AdaptiveAvgPool2d(1),
                    nn.Flatten(),
                )
                for c in CAMERAS
            }
        )
        self.head = nn.Sequential(nn.Linear(TO * (8 * len(CAMERAS) + STATE), 64), nn.ReLU(), nn.Linear(64, TP * A))
        # The state's normalisation travels in the module, as an exported policy's would.
        self.register_buffer("state_mean", torch.tensor([0.5, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0, 0.5]))
        self.register_buffer("state_std", torch.tensor([0.2, 0.2, 0.2, 0.5, 0.5, 0.5, 0.5, 0.5]))

    def forward(self, obs: Dict[str, Tensor]) -> Tensor:
        feats = []
        state = obs["observation.state"]
        b, t = state.shape[0], state.shape[1]
        for name, enc in self.encoders.items():
            x = obs["observation.images." + name]
            feats.append(enc(x.flatten(0, 1)).view(b, t, -1))
        feats.append((state - self.state_mean) / self.state_std)
        h = self.head(torch.cat(feats, -1).flatten(1)).view(b, self.horizon, self.action_dim)
        return torch.cat([torch.tanh(h[..., :6]) * 0.2, torch.sigmoid(h[..., 6:])], -1)


def inputs() -> Dict[str, Tensor]:
    """The test inputs, by formula (labrig's test computes the same in f64, then f32)."""
    obs = {}
    for k, c in enumerate(CAMERAS):
        n = TO * 3 * SIZE * SIZE
        i = torch.arange(n, dtype=torch.float64)
        obs["observation.images." + c] = (torch.sin(0.001 * i + k) * 0.5 + 0.5).float().view(1, TO, 3, SIZE, SIZE)
    state = [[0.45, 0.02, 0.35, 1.0, 0.0, 0.0, 0.0, 0.1], [0.46, 0.01, 0.34, 0.99, 0.1, 0.0, 0.0, 0.2]]
    obs["observation.state"] = torch.tensor(state, dtype=torch.float64).float().view(1, TO, STATE)
    return obs


def main():
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    model = TinyPolicy().eval()
    obs = inputs()
    with torch.no_grad():
        eager = model(obs)
        scripted = torch.jit.script(model)
        traced = torch.jit.trace(model, (obs,), strict=False)
        scripted.save(str(out / "policy_scripted.pt"))
        traced.save(str(out / "policy_traced.pt"))
        # Loaded back, as labrig loads them.
        outs = {
            "eager": eager,
            "scripted": torch.jit.load(str(out / "policy_scripted.pt"))(obs),
            "traced": torch.jit.load(str(out / "policy_traced.pt"))(obs),
        }
    (out / "spec.toml").write_text(
        f"""# labrig's TorchScript policy spec (see ARCHITECTURE.md, "TorchScript policies").
id = "torchscript_tiny"
cameras = {json.dumps(CAMERAS)}
image_size = {SIZE}
image_range = "unit"
state = ["eef_pose", "gripper_position"]
n_obs_steps = {TO}
horizon = {TP}
n_action_steps = 8
action_space = "cartesian_velocity"
action_dim = {A}
rate_hz = 20.0
"""
    )
    expected = {
        "torch": torch.__version__,
        "shape": list(eager.shape),
        **{k: v.flatten().tolist() for k, v in outs.items()},
    }
    (out / "expected.json").write_text(json.dumps(expected))
    for k, v in outs.items():
        print(k, tuple(v.shape), float((v - eager).abs().max()))


if __name__ == "__main__":
    main()
