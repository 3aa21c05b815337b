"""Anchors for the project's speed (issue 17): each row of the project's work, timed next to
the same work in MuJoCo or PyTorch, back to back in one run, with the ratio printed.

Run through scripts/bench-anchors, which installs the pinned torch and mujoco into a cached
venv and hands this script the command of the project's side
(`cargo bench -p crawler-learner --bench anchors --`, learner/benches/anchors.rs). The
workloads here mirror that file row by row. Everything runs on one thread.

  physics              10 x 20 s of the square-wave gait that crawls in both engines
                       (actor/env/src/gait.rs, FORWARD) from joint angles (0, 0): this
                       project's rapier3d env against MuJoCo's C rollout (mujoco.rollout) of
                       the study's model. Speed and flips in both are printed too: a faster
                       engine that is wrong does not count.
  inference-b{1,8,16}  the study network's forward pass: plain Rust against tch (both
                       measured by the Rust bench, in one process).
  update-*             one Double DQN update (online and target forward on s', online
                       forward and backward on s, the loss, the gradient norm, clipping where
                       configured, Adam): the learner's libtorch path against PyTorch with
                       Adam(fused=True), as a PyTorch user would write it.

Each row is measured --repeat times (default 3), project then anchor each time; the line
gives the medians and the spread of the ratios. Output: one line per row on stderr and, with
--json, the rows as JSON lines on stdout.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import time
from pathlib import Path

import mujoco
import numpy as np
import torch
from mujoco import rollout

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "mujoco"))
from check import Crawler, square_wave  # noqa: E402  (the cross-check's model and reset)

BUDGET_S = 3.0
OBS_DIM = 40
NUM_ACTIONS = 25
# actor/env/src/gait.rs: SquareWaveGait::FORWARD.
FORWARD_GAIT = {"period": 0.3, "high": [-1.0, 0.5], "low": [0.0, -0.5], "phase_lag": 0.0}
PHYSICS_EPISODES, PHYSICS_STEPS = 10, 10_000
# learner/benches/anchors.rs: NetworkSpec::study() and the default preset's network.
STUDY_NET = dict(hidden=[512, 256, 128], layer_norm=True)
DEFAULT_NET = dict(hidden=[256, 256], layer_norm=True)
UPDATES = {
    "update-study-b32": dict(net=STUDY_NET, batch=32, loss="mse", clip=None, gamma=0.99),
    "update-study-b256": dict(net=STUDY_NET, batch=256, loss="mse", clip=None, gamma=0.99),
    "update-default-b32": dict(net=DEFAULT_NET, batch=32, loss="huber", clip=10.0, gamma=0.98),
    "update-default-b64": dict(net=DEFAULT_NET, batch=64, loss="huber", clip=10.0, gamma=0.98),
    "update-default-b256": dict(net=DEFAULT_NET, batch=256, loss="huber", clip=10.0, gamma=0.98),
}


def rate(f) -> float:
    """Calls per second of f over about BUDGET_S, after one warm-up call."""
    f()
    calls, start = 0, time.perf_counter()
    while time.perf_counter() - start < BUDGET_S:
        f()
        calls += 1
    return calls / (time.perf_counter() - start)


def physics_anchor() -> dict:
    crawler = Crawler()
    crawler.reset(0.0, 0.0)
    model, data = crawler.model, crawler.data
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    initial = np.zeros(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, initial, spec)
    dt = model.opt.timestep
    # The Rust gait computes t in f32; the square wave's edges land on the same steps.
    times = (np.arange(PHYSICS_STEPS, dtype=np.float32) * np.float32(dt)).astype(np.float64)
    control = np.array([square_wave(FORWARD_GAIT, t) for t in times])[None, :, :]
    initial_states = np.tile(initial, (PHYSICS_EPISODES, 1))
    rollout.rollout(model, data, initial_states[:1], control[:, :100, :])  # warm-up
    start = time.perf_counter()
    states, _ = rollout.rollout(model, data, initial_states, control)
    seconds = time.perf_counter() - start
    # FULLPHYSICS: time, then qpos (x, y, z, quaternion w x y z, q1, q2), ...
    x = states[:, :, 1]
    qx, qy = states[:, :, 5], states[:, :, 6]
    up_z = 1.0 - 2.0 * (qx**2 + qy**2)
    flipped = up_z < 0.0
    flips = int(np.sum(flipped[:, 1:] & ~flipped[:, :-1]) + np.sum(flipped[:, 0]))
    speed = float(np.mean(x[:, -1] - initial[1]) / (PHYSICS_STEPS * dt))
    steps = PHYSICS_EPISODES * PHYSICS_STEPS
    return {"anchor": steps / seconds, "anchor_name": f"MuJoCo {mujoco.__version__} C rollout",
            "anchor_speed": speed, "anchor_flips": flips}


def q_network(hidden, layer_norm) -> torch.nn.Sequential:
    layers, inputs = [], OBS_DIM
    for width in hidden:
        layers.append(torch.nn.Linear(inputs, width))
        if layer_norm:
            layers.append(torch.nn.LayerNorm(width))
        layers.append(torch.nn.ReLU())
        inputs = width
    layers.append(torch.nn.Linear(inputs, NUM_ACTIONS))
    return torch.nn.Sequential(*layers)


def update_anchor(row: str) -> dict:
    cfg = UPDATES[row]
    torch.manual_seed(1)
    online = q_network(**cfg["net"])
    target = q_network(**cfg["net"])
    target.load_state_dict(online.state_dict())
    params = list(online.parameters())
    optimizer = torch.optim.Adam(params, lr=5e-4, eps=1e-8, fused=True)
    b = cfg["batch"]
    obs, next_obs = torch.randn(b, OBS_DIM), torch.randn(b, OBS_DIM)
    actions = torch.randint(NUM_ACTIONS, (b,))
    returns, discounts = torch.randn(b), torch.full((b,), cfg["gamma"])
    loss_fn = torch.nn.functional.mse_loss if cfg["loss"] == "mse" else torch.nn.functional.huber_loss

    def update():
        with torch.no_grad():
            best = online(next_obs).argmax(1, keepdim=True)
            targets = returns + discounts * target(next_obs).gather(1, best).squeeze(1)
        q = online(obs).gather(1, actions.unsqueeze(1)).squeeze(1)
        loss = loss_fn(q, targets)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if cfg["clip"] is None:
            norm = torch.nn.utils.get_total_norm([p.grad for p in params])
        else:
            norm = torch.nn.utils.clip_grad_norm_(params, cfg["clip"])
        loss_value, norm_value = loss.item(), norm.item()
        if math.isfinite(loss_value) and math.isfinite(norm_value):  # the learner's guard
            optimizer.step()
        td_errors = (q - targets).detach().abs().numpy()
        return loss_value, q.detach().mean().item(), td_errors

    return {"anchor": rate(update), "anchor_name": f"PyTorch {torch.__version__.split('+')[0]}, fused Adam"}


def project(command: list[str], row: str) -> dict:
    out = subprocess.run([*command, row], check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", nargs="*", default=["physics", "inference-b1", "inference-b8", "inference-b16",
                                                      *UPDATES])
    parser.add_argument("--repeat", type=int, default=3, help="back-to-back pairs per row (medians reported)")
    parser.add_argument("--json", action="store_true", help="also print the rows as JSON lines on stdout")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="the project's side: a command taking a row")
    args = parser.parse_args()
    command = [c for c in args.command if c != "--"]
    if not command:
        sys.exit("error: give the project's bench command after --, e.g. -- cargo bench -p crawler-learner "
                 "--bench anchors --")
    torch.set_num_threads(1)
    results = []
    print(f"{'row':<20} {'project':>12} {'anchor':>12}  unit       ratio (higher: project ahead)  anchor", file=sys.stderr)
    for row in args.rows:
        # Each repeat times the project and then its anchor, back to back; the medians are
        # reported, so that one noisy second on a shared machine does not decide a row.
        repeats = []
        for _ in range(args.repeat):
            result = project(command, row)
            if row == "physics":
                result |= physics_anchor()
            elif row in UPDATES:
                result |= update_anchor(row)
            # For times (µs) the project is ahead when its time is smaller.
            lower_is_better = result["unit"] == "µs"
            result["ratio"] = (result["anchor"] / result["project"] if lower_is_better
                               else result["project"] / result["anchor"])
            repeats.append(result)
        result = dict(repeats[0])
        for key in ("project", "anchor", "ratio"):
            result[key] = statistics.median(r[key] for r in repeats)
        result["ratios"] = [round(r["ratio"], 3) for r in repeats]
        results.append(result)
        extra = ""
        if row == "physics":
            extra = (f"  (speed {result['speed']:.3f} m/s, {result['flips']} flips here; "
                     f"{result['anchor_speed']:.3f} m/s, {result['anchor_flips']} flips there)")
        spread = f"{min(result['ratios']):.2f}-{max(result['ratios']):.2f}"
        print(f"{row:<20} {result['project']:>12.1f} {result['anchor']:>12.1f}  {result['unit']:<10} "
              f"{result['ratio']:>5.2f}x (of {args.repeat}: {spread})   {result['anchor_name']}{extra}", file=sys.stderr)
    if args.json:
        for result in results:
            print(json.dumps(result))


if __name__ == "__main__":
    main()
