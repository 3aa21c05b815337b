"""Cross-simulator check: this project's crawler against the study's own MuJoCo model.

Run through scripts/mujoco-check, which installs the pinned MuJoCo into a cached venv.

  eval CHECKPOINTS   greedy episodes of a checkpoint in MuJoCo, on the study's model
                     (crawling_robot.xml, a copy of the study's MJCF), with the observation
                     built as actor/env/src/observation.rs documents it and the checkpoint's
                     own action levels, torque limit, action repeat and direction. Prints one
                     JSON object: per-episode speed, flips, joint-limit overshoot, and the
                     summary (mean, min, stuck episodes).
  scan CHECKPOINTS    every kept checkpoint of a run (every --every'th step-* directory, then
                     its average and best) played as eval plays one: a JSON line each, then
                     the fastest of those upright (no flip, no stuck episode) in every episode.
                     Its start poses come from another seed than eval's, so a checkpoint
                     chosen from a scan is confirmed by eval on starts it was not chosen on.
  observe Q1 Q2      the observation after a reset to joint angles (Q1, Q2) in radians and
                     --steps physics steps of the constant --torques, as JSON: the layout
                     check against the Rust env (tests/tests/outputs.rs).
  act CHECKPOINTS    greedy actions of a checkpoint's network for observations given as
                     JSON lists, one per line on stdin: the numpy MLP against the Rust one.
  gaits              the gait bank (actor/env/examples/gait_bank.rs prints it, with each gait's
                     start poses, mean speed and flips in this project's env, as JSON lines
                     on stdin) run in MuJoCo: each gait's speed and flips in both engines,
                     their rank correlation and mean absolute difference.
  replay             sim-to-sim state replay: a square-wave gait is run in MuJoCo, and from
                     every --every'th state of that trajectory this project's env
                     (actor/env/examples/state_replay.rs) is set to the same qpos/qvel and plays
                     the same torques for --horizon steps. Prints, per horizon, how far the
                     two engines drift apart (base tilt, joint angles, rates), the normal
                     and landing impulse on the base over 1, 5 and --horizon steps in both,
                     and what this engine does from the states where MuJoCo's base is about
                     to tip over.
  solvers            a square-wave gait on the study's model under each of MuJoCo's solvers
                     (the model's PGS, Newton, CG, PGS with elliptic cones): speed, flips
                     and how far the base rolls. Shows whether a gait's roll comes from the
                     solver's uneven contact solve (Newton keeps the crawler in its plane) or
                     from the gait's dynamics (every solver rolls it).

No torch: checkpoints are read with safetensors and run by a numpy MLP.
"""

from __future__ import annotations

import argparse
import subprocess
import json
import math
import sys
from pathlib import Path

import mujoco
import numpy as np
from safetensors.numpy import load_file

MODEL = Path(__file__).with_name("crawling_robot.xml")
SHOULDER_PAIR = '<pair geom1="base_geom" geom2="link1_geom" condim="3"/>'
DEG = math.pi / 180.0
JOINT1_RANGE = (-80.0 * DEG, 80.0 * DEG)
JOINT2_RANGE = (0.0, 150.0 * DEG)
# Geometry used to lift a start pose clear of the floor, as the Rust env does (model.rs).
BASE_HALF, LINK1_LENGTH, LINK2_LENGTH, LINK_RADIUS, TIP_HALF, FLOOR_Z = 0.05, 0.20, 0.24, 0.01, 0.01, -0.05
BASE_IMPACT_THRESHOLD = 50.0  # N: the Rust env's default `base_impact_threshold`
STUCK_SPEED = 0.05  # m/s: an episode slower than this is stuck (issue 18's definition)


def rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def start_lift(q1: float, q2: float) -> float:
    """How far to lift a crawler posed with its base at rest so no part is below the floor
    (actor/env/src/crawler/world.rs, start_lift)."""
    r1, r2 = rot_y(q1), rot_y(q1 + q2)
    link1_origin = np.array([BASE_HALF, 0.0, 0.0])
    link2_origin = link1_origin + r1 @ np.array([LINK1_LENGTH, 0.0, 0.0])
    lowest = -BASE_HALF
    lowest = min(lowest, link2_origin[2] - LINK_RADIUS)
    link2_end = link2_origin + r2 @ np.array([LINK2_LENGTH, 0.0, 0.0])
    lowest = min(lowest, link2_end[2] - LINK_RADIUS)
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                corner = np.array([LINK2_LENGTH + sx * TIP_HALF, sy * TIP_HALF, sz * TIP_HALF])
                lowest = min(lowest, (link2_origin + r2 @ corner)[2])
    return max(FLOOR_Z - lowest, 0.0)


class Crawler:
    """The study's model with a clean reset: base at rest, joints at (q1, q2), zero velocity."""

    def __init__(self, without_shoulder_pair: bool = False) -> None:
        if without_shoulder_pair:
            # The MJCF's base–link 1 contact pair left out: what it does to the shoulder is
            # the difference (`pair`).
            xml = MODEL.read_text()
            if SHOULDER_PAIR not in xml:
                sys.exit(f"error: {MODEL} has no `{SHOULDER_PAIR}` to leave out; update SHOULDER_PAIR in check.py")
            self.model = mujoco.MjModel.from_xml_string(xml.replace(SHOULDER_PAIR, ""))
        else:
            self.model = mujoco.MjModel.from_xml_path(str(MODEL))
        self.data = mujoco.MjData(self.model)
        self.dt = self.model.opt.timestep
        self.base_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "base_geom")
        self.link1_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "link1_geom")

    def reset(self, q1: float, q2: float) -> None:
        q1 = min(max(q1, JOINT1_RANGE[0]), JOINT1_RANGE[1])
        q2 = min(max(q2, JOINT2_RANGE[0]), JOINT2_RANGE[1])
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[0:3] = [0.0, 0.0, start_lift(q1, q2)]
        self.data.qpos[3:7] = [1.0, 0.0, 0.0, 0.0]
        self.data.qpos[7:9] = [q1, q2]
        mujoco.mj_forward(self.model, self.data)
        self.stepped = False  # no contact solve yet: touch forces read 0, as in the Rust env
        self.flipped = False
        self.flips = 0
        self.overshoot = 0.0  # largest excursion beyond a joint limit, radians
        self.steps = 0
        self.overshoot_sum = 0.0  # both joints' excursions beyond their limits, summed over steps (rad)
        self.steps_past_limit = 0
        self.impact_impulse = 0.0  # base contact force above the threshold, integrated (N·s)
        self.start_x = float(self.data.qpos[0])

    def step(self, torques) -> None:
        self.data.ctrl[:] = torques
        mujoco.mj_step(self.model, self.data)
        self.stepped = True
        up_z = self.rotation()[2, 2]
        flipped = up_z < 0.0
        if flipped and not self.flipped:
            self.flips += 1
        self.flipped = flipped
        q1, q2 = self.data.qpos[7], self.data.qpos[8]
        past = (max(JOINT1_RANGE[0] - q1, q1 - JOINT1_RANGE[1], 0.0), max(JOINT2_RANGE[0] - q2, q2 - JOINT2_RANGE[1], 0.0))
        self.overshoot = max(self.overshoot, *past)
        # What env.joint_limit_penalty charges: both joints' excursions, summed.
        both = past[0] + past[1]
        self.steps += 1
        self.overshoot_sum += both
        self.steps_past_limit += both > 0.0
        self.impact_impulse += self.dt * max(self.base_contact_force() - BASE_IMPACT_THRESHOLD, 0.0)

    def base_contact_force(self) -> float:
        """The normal force on the base's contacts (N), as the Rust env's `base_contact_force`:
        every contact of the base but the base–link 1 pair, which the port models as a
        constraint on the shoulder's rate (env.shoulder_pair)."""
        total, force = 0.0, np.zeros(6)
        for i in range(self.data.ncon):
            geoms = (self.data.contact[i].geom1, self.data.contact[i].geom2)
            if self.base_geom in geoms and self.link1_geom not in geoms:
                mujoco.mj_contactForce(self.model, self.data, i, force)
                total += abs(force[0])
        return total

    def rotation(self) -> np.ndarray:
        matrix = np.zeros(9)
        mujoco.mju_quat2Mat(matrix, self.data.qpos[3:7])
        return matrix.reshape(3, 3)

    def distance(self, direction: float) -> float:
        return direction * (float(self.data.qpos[0]) - self.start_x)

    def observe(self, previous_torques) -> np.ndarray:
        """The 40 values of actor/env/src/observation.rs, from the current state. Touch forces
        are those of the last step's contact solve (MuJoCo computes sensors before it
        integrates), as in the Rust env; link angular velocities are composed from the
        current base angular velocity and joint rates (world frame)."""
        qpos, qvel = self.data.qpos, self.data.qvel
        rotation = self.rotation()
        base_angvel_world = rotation @ qvel[3:6]
        axis_world = rotation @ np.array([0.0, 1.0, 0.0])  # both hinges turn about the base's y
        link1 = base_angvel_world + qvel[6] * axis_world
        link2 = link1 + qvel[7] * axis_world
        touches = self.data.sensordata[6:23] if self.stepped else np.zeros(17)
        return np.concatenate(
            [[qpos[2]], qpos[3:7], qpos[7:9], qvel[0:3], qvel[3:6], qvel[6:8], link1, link2, touches, previous_torques]
        ).astype(np.float32)


class Mlp:
    """The checkpoint's Q-network (actor/env/src/policy/spec.rs): Linear, LayerNorm?, ReLU per
    hidden layer, then a Linear, with nn.Sequential names."""

    def __init__(self, weights: dict, network: dict) -> None:
        stride = 3 if network.get("layer_norm", True) else 2
        self.layers = []
        for i in range(len(network["hidden"])):
            index = stride * i
            norm = None
            if stride == 3:
                norm = (weights[f"{index + 1}.weight"], weights[f"{index + 1}.bias"])
            self.layers.append((weights[f"{index}.weight"], weights[f"{index}.bias"], norm))
        last = stride * len(network["hidden"])
        self.output = (weights[f"{last}.weight"], weights[f"{last}.bias"])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Q-values of one input (a vector) or of a batch of them (one per row)."""
        for weight, bias, norm in self.layers:
            x = x @ weight.T + bias
            if norm is not None:
                mean, var = x.mean(axis=-1, keepdims=True), x.var(axis=-1, keepdims=True)
                x = (x - mean) / np.sqrt(var + 1e-5) * norm[0] + norm[1]
            x = np.maximum(x, 0.0)
        return x @ self.output[0].T + self.output[1]


class PolicyInput:
    """The policy's input of actor/env/src/observation.rs (`stack_first`, `stack_next`): the
    last `history` 40-value observations of the decisions so far, newest first, the first one
    repeated where the episode is younger than the history."""

    def __init__(self, env: dict) -> None:
        self.history = int(env.get("observation_history", 1))
        self.values = np.zeros(0)

    def first(self, frame: np.ndarray) -> np.ndarray:
        self.values = np.tile(frame, self.history)
        return self.values

    def next(self, frame: np.ndarray) -> np.ndarray:
        self.values = np.concatenate([frame, self.values[: len(self.values) - len(frame)]])
        return self.values


def step_checkpoints(path: Path) -> list[Path]:
    """A run's step-* checkpoints in training order."""
    return sorted(
        (p for p in path.glob("step-*") if (p / "meta.json").exists()), key=lambda p: int(p.name.split("-")[1])
    )


def newest_checkpoint(path: Path) -> Path:
    if (path / "meta.json").exists():
        return path
    steps = step_checkpoints(path)
    if not steps:
        sys.exit(f"error: no checkpoint in {path}; point at a run's checkpoints directory or a step-* directory")
    return steps[-1]


def load_policy(path: Path) -> tuple[Path, dict, Mlp]:
    checkpoint = newest_checkpoint(path)
    meta = json.loads((checkpoint / "meta.json").read_text())
    return checkpoint, meta, Mlp(load_file(str(checkpoint / "weights.safetensors")), meta["network"])


def action_torques(env: dict):
    """The checkpoint env's map from an action index to the torque pair (τ1, τ2): n levels per
    joint spread over ±τmax, index a giving joint 1 level a // n and joint 2 level a % n."""
    levels = int(env.get("action_levels", 5))
    max_torque = float(env.get("max_torque", 1.0))

    def torque(level: int) -> float:
        return -max_torque + 2.0 * max_torque * level / max(levels - 1, 1)

    return lambda action: np.array([torque(action // levels), torque(action % levels)])


def act(args) -> None:
    _, _, policy = load_policy(Path(args.checkpoints))
    for line in sys.stdin:
        if line.strip():
            observation = np.array(json.loads(line), dtype=np.float32)
            print(int(np.argmax(policy(observation))))


def play(checkpoint: Path, meta: dict, policy: Mlp, episodes: int, seconds: float, seed: int,
         action_repeat: int | None = None) -> dict:
    """Greedy episodes of one checkpoint on the study's model: each episode's speed, flips,
    joint-limit overshoot and base landings, and their summary."""
    env = meta["config"].get("env", {})
    torques_of = action_torques(env)
    repeat = int(action_repeat or env.get("action_repeat", 1))
    direction = -1.0 if env.get("direction", "forward") == "backward" else 1.0
    start1 = env.get("start_joint1_deg", [-45.0, 0.0])
    start2 = env.get("start_joint2_deg", [-22.5, 22.5])

    # The episodes run in lockstep, so that the network answers all of them in one batch.
    rng = np.random.default_rng(seed)
    crawlers = []
    for _ in range(episodes):
        q1 = rng.uniform(*start1) * DEG
        q2 = rng.uniform(*start2) * DEG
        crawler = Crawler()
        crawler.reset(q1, q2)
        crawlers.append(crawler)
    steps = round(seconds / crawlers[0].dt)
    inputs = [PolicyInput(env) for _ in crawlers]
    torques = [np.zeros(2) for _ in crawlers]
    step = 0
    while step < steps:
        batch = np.stack([
            source.first(crawler.observe(held)) if step == 0 else source.next(crawler.observe(held))
            for crawler, source, held in zip(crawlers, inputs, torques)
        ])
        torques = [torques_of(int(action)) for action in np.argmax(policy(batch), axis=-1)]
        held_for = min(repeat, steps - step)
        for crawler, held in zip(crawlers, torques):
            for _ in range(held_for):
                crawler.step(held)
        step += held_for
    played = [
        {
            "speed": crawler.distance(direction) / seconds,
            "flips": crawler.flips,
            "joint_limit_overshoot_deg": crawler.overshoot / DEG,
            "share_of_steps_past_a_limit": crawler.steps_past_limit / max(crawler.steps, 1),
            "mean_limit_overshoot_rad": crawler.overshoot_sum / max(crawler.steps, 1),
            "base_impact_impulse": crawler.impact_impulse,
        }
        for crawler in crawlers
    ]
    speeds = np.array([e["speed"] for e in played])
    summary = {
        "mean_speed": float(speeds.mean()),
        "std_speed": float(speeds.std()),
        "min_speed": float(speeds.min()),
        "stuck_episodes": int((speeds < STUCK_SPEED).sum()),
        "flips": int(sum(e["flips"] for e in played)),
        "max_joint_limit_overshoot_deg": float(max(e["joint_limit_overshoot_deg"] for e in played)),
        "share_of_steps_past_a_limit": float(np.mean([e["share_of_steps_past_a_limit"] for e in played])),
        "mean_limit_overshoot_rad": float(np.mean([e["mean_limit_overshoot_rad"] for e in played])),
        "mean_base_impact_impulse": float(np.mean([e["base_impact_impulse"] for e in played])),
    }
    return {
        "engine": f"mujoco {mujoco.__version__}",
        "checkpoint": str(checkpoint),
        "action_repeat": repeat,
        "episodes": played,
        "summary": summary,
    }


def evaluate(args) -> None:
    if args.episodes < 1:
        sys.exit("error: --episodes must be at least 1")
    checkpoint, meta, policy = load_policy(Path(args.checkpoints))
    report = play(checkpoint, meta, policy, args.episodes, args.seconds, args.seed, args.action_repeat)
    summary, episodes = report["summary"], report["episodes"]
    json.dump(report, sys.stdout)
    print()
    print(
        f"MuJoCo: {summary['mean_speed']:.3f} ± {summary['std_speed']:.3f} m/s, min {summary['min_speed']:.3f}, "
        f"{summary['stuck_episodes']}/{len(episodes)} stuck, {summary['flips']} flips, "
        f"overshoot ≤ {summary['max_joint_limit_overshoot_deg']:.1f}° "
        f"({summary['share_of_steps_past_a_limit']:.0%} of steps past a limit), "
        f"base landings {summary['mean_base_impact_impulse']:.2f} N·s over {BASE_IMPACT_THRESHOLD:.0f} N",
        file=sys.stderr,
    )


def scanned_checkpoints(path: Path, every: int) -> list[Path]:
    """A run's checkpoints in training order (every `every`-th step-* directory), then its
    `average` and `best` where the run kept them."""
    chosen = step_checkpoints(path)[::-1][::every][::-1]  # counted back from the newest, so the newest is in
    chosen += [path / name for name in ("average", "best") if (path / name / "meta.json").exists()]
    if not chosen:
        sys.exit(f"error: no checkpoint in {path}; point at a run's checkpoints directory")
    return chosen


def scan(args) -> None:
    """Every kept checkpoint of a run on the study's model, the sim-to-sim check of each
    candidate a run could ship (legged_gym's and humanoid-gym's play-in-MuJoCo step, over a
    whole run rather than one checkpoint)."""
    if args.episodes < 1 or args.every < 1:
        sys.exit("error: --episodes and --every must be at least 1")
    rows = []
    for checkpoint in scanned_checkpoints(Path(args.checkpoints), args.every):
        _, meta, policy = load_policy(checkpoint)
        summary = play(checkpoint, meta, policy, args.episodes, args.seconds, args.seed)["summary"]
        row = {"checkpoint": str(checkpoint), "updates": meta.get("progress", {}).get("updates"), **summary}
        rows.append(row)
        print(json.dumps(row), flush=True)
    upright = sorted(
        (r for r in rows if r["flips"] == 0 and r["stuck_episodes"] == 0), key=lambda r: -r["mean_speed"]
    )
    print(f"{len(upright)} of {len(rows)} checkpoints crawl upright in all {args.episodes} episodes "
          f"(seed {args.seed}); the fastest:", file=sys.stderr)
    for r in upright[: args.top]:
        print(f"  {r['mean_speed']:.3f} ± {r['std_speed']:.3f} m/s, min {r['min_speed']:.3f}  {r['checkpoint']}",
              file=sys.stderr)


def square_wave(gait: dict, t: float) -> list:
    def first_half(phase: float) -> bool:
        return (t / gait["period"] - phase) % 1.0 < 0.5

    torque = lambda j, phase: gait["high"][j] if first_half(phase) else gait["low"][j]  # noqa: E731
    return [torque(0, 0.0), torque(1, gait["phase_lag"])]


def ranks(values: np.ndarray) -> np.ndarray:
    order = values.argsort(kind="stable")
    ranked = np.empty(len(values))
    ranked[order] = np.arange(len(values))
    for value in np.unique(values):  # ties share their mean rank
        tied = values == value
        ranked[tied] = ranked[tied].mean()
    return ranked


def gaits(args) -> None:
    bank = [json.loads(line) for line in sys.stdin if line.strip()]
    if not bank:
        sys.exit("error: no gaits on stdin; pipe in `cargo run --release -p crawler-env --example gait_bank`")
    crawler = Crawler()
    rows = []
    for entry in bank:
        gait = entry["gait"]
        steps = round(entry["seconds"] / crawler.dt)
        distance, flips, overshoot, rocking = 0.0, 0, 0.0, 0.0
        for q1, q2 in entry["starts"]:
            crawler.reset(q1, q2)
            for s in range(steps):
                crawler.step(square_wave(gait, s * crawler.dt))
                # The free joint's angular velocity is in the base's own frame.
                rocking += float(crawler.data.qvel[3] ** 2 + crawler.data.qvel[4] ** 2)
            distance += crawler.distance(1.0)
            flips += crawler.flips
            overshoot = max(overshoot, crawler.overshoot / DEG)
        rows.append(
            {
                "gait": gait,
                "rapier": {
                    "speed": entry["speed"],
                    "flips": entry["flips"],
                    "overshoot_deg": entry["overshoot_deg"],
                    "rocking": entry.get("rocking", float("nan")),
                },
                "mujoco": {
                    "speed": distance / (entry["seconds"] * len(entry["starts"])),
                    "flips": flips,
                    "overshoot_deg": overshoot,
                    "rocking": rocking / (steps * len(entry["starts"])),
                },
            }
        )
        print(json.dumps(rows[-1]))
        sys.stdout.flush()
    ours = np.array([r["rapier"]["speed"] for r in rows])
    theirs = np.array([r["mujoco"]["speed"] for r in rows])
    correlation = float(np.corrcoef(ranks(ours), ranks(theirs))[0, 1])
    mad = float(np.abs(ours - theirs).mean())
    flips_ours = sum(r["rapier"]["flips"] > 0 for r in rows)
    flips_theirs = sum(r["mujoco"]["flips"] > 0 for r in rows)
    flip_agreement = sum((r["rapier"]["flips"] > 0) == (r["mujoco"]["flips"] > 0) for r in rows)
    overshoot = {engine: float(np.median([r[engine]["overshoot_deg"] for r in rows])) for engine in ("rapier", "mujoco")}
    # How hard the base rocks (mean ωx² + ωy², its own frame) on the gaits that stay upright
    # in both engines: a tumble's spin would swamp it. MuJoCo over this engine, median.
    upright = [r for r in rows if r["rapier"]["flips"] == 0 and r["mujoco"]["flips"] == 0]
    rocking_ratio = (
        float(np.median([r["mujoco"]["rocking"] / r["rapier"]["rocking"] for r in upright])) if upright else float("nan")
    )
    summary = {
        "gaits": len(rows),
        "spearman": correlation,
        "mean_abs_speed_difference": mad,
        "gaits_flipping": {"rapier": flips_ours, "mujoco": flips_theirs},
        "flip_agreement": flip_agreement,
        "median_overshoot_deg": overshoot,
        "upright_in_both": len(upright),
        "rocking_mujoco_over_rapier": rocking_ratio,
    }
    print(json.dumps({"summary": summary}))
    print(
        f"{len(rows)} gaits: Spearman {correlation:.3f}, mean |Δspeed| {mad:.3f} m/s, gaits that flip: "
        f"rapier {flips_ours}, MuJoCo {flips_theirs}, agreeing on flips {flip_agreement}/{len(rows)}, "
        f"median joint-limit overshoot: rapier {overshoot['rapier']:.1f}°, MuJoCo {overshoot['mujoco']:.1f}°, "
        f"base rocking MuJoCo/rapier {rocking_ratio:.2f} (median over the {len(upright)} gaits upright in both)",
        file=sys.stderr,
    )


def tilt_deg(quaternion) -> float:
    """Angle between the base's up axis and the world's, in degrees."""
    w, x, y, z = quaternion
    up_z = 1.0 - 2.0 * (x * x + y * y)
    return math.degrees(math.acos(max(-1.0, min(1.0, up_z))))


def pitch_deg(quaternion) -> float:
    """The base's rotation about y (xyz Euler angles), in degrees: the upright reward's pitch."""
    w, x, y, z = quaternion
    return math.degrees(math.asin(max(-1.0, min(1.0, 2.0 * (w * y - x * z)))))


def contact_phase(crawler: Crawler) -> str:
    """What the crawler in MuJoCo is doing now: a joint past its limit, else which of its
    parts touch the floor."""
    q1, q2 = crawler.data.qpos[7], crawler.data.qpos[8]
    if not (JOINT1_RANGE[0] <= q1 <= JOINT1_RANGE[1] and JOINT2_RANGE[0] <= q2 <= JOINT2_RANGE[1]):
        return "past a limit"
    model, data = crawler.model, crawler.data
    floor = model.geom("floor").id
    touching = set()
    for contact in data.contact[: data.ncon]:
        if floor in (contact.geom1, contact.geom2):
            other = contact.geom2 if contact.geom1 == floor else contact.geom1
            touching.add(model.geom(other).name)
    names = {"base_geom": "base", "link1_geom": "link 1", "link2_geom": "link 2", "link2_termination": "tip"}
    down = [label for geom, label in names.items() if geom in touching]
    return " + ".join(down) + " on the floor" if down else "airborne"


def replay(args) -> None:
    gait = gait_from_args(args.gait)
    crawler = Crawler()
    steps = round(args.seconds / crawler.dt)
    horizon = args.horizon
    if args.checkpoint:
        # A policy's own trajectory on the study's model: its greedy torques, held for its
        # action repeat, are what this engine then plays from each state.
        _, meta, policy = load_policy(Path(args.checkpoint))
        env = meta["config"].get("env", {})
        torques_of = action_torques(env)
        repeat = int(env.get("action_repeat", 1))
        inputs = PolicyInput(env)
        gait = {"checkpoint": args.checkpoint, "action_repeat": repeat}
    qpos, qvel, torques, phases, base_forces = [], [], [], [], []
    crawler.reset(args.start[0] * DEG, args.start[1] * DEG)
    crawler.data.qpos[2] += args.lift
    mujoco.mj_forward(crawler.model, crawler.data)
    torque = np.zeros(2)
    for s in range(steps + horizon):
        qpos.append(crawler.data.qpos.copy())
        qvel.append(crawler.data.qvel.copy())
        phases.append(contact_phase(crawler))
        if not args.checkpoint:
            torque = square_wave(gait, s * crawler.dt)
        elif s % repeat == 0:
            frame = crawler.observe(torque)
            action = int(np.argmax(policy(inputs.first(frame) if s == 0 else inputs.next(frame))))
            torque = torques_of(action)
        torques.append(torque)
        crawler.step(torque)
        base_forces.append(crawler.base_contact_force())
    qpos.append(crawler.data.qpos.copy())
    qvel.append(crawler.data.qvel.copy())
    starts = list(range(0, steps, args.every))
    queries = "".join(
        json.dumps(
            {
                "qpos": [float(v) for v in qpos[s]],
                "qvel": [float(v) for v in qvel[s]],
                "torques": [[float(t) for t in pair] for pair in torques[s : s + horizon]],
            }
        )
        + "\n"
        for s in starts
    )
    replies = run_state_replay(args.rapier, args.overrides, queries, len(starts))

    # Drift of this engine from MuJoCo after h steps from the same state, over all starts.
    horizons = sorted({1, 5, 25, horizon} & set(range(1, horizon + 1)))
    measures = {
        "tilt_deg": lambda p, v: tilt_deg(p[3:7]),
        "pitch_deg": lambda p, v: pitch_deg(p[3:7]),
        "q1_deg": lambda p, v: math.degrees(p[7]),
        "q2_deg": lambda p, v: math.degrees(p[8]),
        "x_mm": lambda p, v: 1000.0 * p[0],
        "z_mm": lambda p, v: 1000.0 * p[2],
        "pitch_rate": lambda p, v: v[4],
        "q1_rate": lambda p, v: v[6],
        "q2_rate": lambda p, v: v[7],
    }
    table = {}
    for h in horizons:
        row = {}
        for name, measure in measures.items():
            differences = np.array(
                [measure(np.array(reply[h - 1]["qpos"]), np.array(reply[h - 1]["qvel"])) - measure(qpos[s + h], qvel[s + h])
                 for s, reply in zip(starts, replies)]
            )
            row[name] = {"mean_abs": float(np.abs(differences).mean()), "mean": float(differences.mean())}
        # How far the base gets here against there from the same states: a lead that grows
        # with the horizon is ground this engine gains that a policy trained here banks on.
        theirs = float(np.mean([qpos[s + h][0] - qpos[s][0] for s in starts]))
        ours = float(np.mean([reply[h - 1]["qpos"][0] - qpos[s][0] for s, reply in zip(starts, replies)]))
        row["progress_ratio"] = ours / theirs if abs(theirs) > 1e-9 else None
        table[h] = row
    # One-step differences by what the crawler is doing at the start: where the engines
    # disagree about single steps says which part of the physics differs.
    by_phase = {}
    for phase in sorted(set(phases[s] for s in starts)):
        chosen = [(s, reply) for s, reply in zip(starts, replies) if phases[s] == phase]
        row = {"replays": len(chosen)}
        for name in ("pitch_rate", "q1_rate", "q2_rate"):
            measure = measures[name]
            row[name] = float(np.mean([
                abs(measure(np.array(reply[0]["qpos"]), np.array(reply[0]["qvel"])) - measure(qpos[s + 1], qvel[s + 1]))
                for s, reply in chosen
            ]))
        by_phase[phase] = row
    # The base's contact force from the same states under the same torques: whether the two
    # contact models load the base alike (what the landing penalty charges), apart from how a
    # gait plays out over a whole episode. Impulses are per replay, over the first 5 steps
    # (near-identical states) and over the whole horizon; "landing" is the part above the
    # penalty's threshold, as eval reports it.
    def impulses(forces) -> tuple:
        forces = np.asarray(forces, dtype=float)
        return crawler.dt * forces.sum(), crawler.dt * np.maximum(forces - BASE_IMPACT_THRESHOLD, 0.0).sum()

    contact = {}
    # Only windows the replies cover: each holds `horizon` steps.
    for window in sorted({1, 5, horizon} & set(range(1, horizon + 1))):
        ours = [impulses([state["base_force"] for state in reply[:window]]) for reply in replies]
        theirs = [impulses(base_forces[s : s + window]) for s in starts]
        total_ours, landing_ours = (float(v) for v in np.sum(ours, axis=0))
        total_theirs, landing_theirs = (float(v) for v in np.sum(theirs, axis=0))
        landed = [i for i, pair in enumerate(theirs) if pair[1] > 0.0]
        contact[window] = {
            "normal_impulse_ns": {"rapier": total_ours, "mujoco": total_theirs},
            "landing_impulse_ns": {"rapier": landing_ours, "mujoco": landing_theirs},
            "replays_landing_in_mujoco": len(landed),
            "of_those_landing_here": int(sum(ours[i][1] > 0.0 for i in landed)),
            "replays_landing_here": int(sum(pair[1] > 0.0 for pair in ours)),
        }
    # Over the same stretch of trajectory: the replays reach `horizon` steps past the last start.
    peaks = {"rapier": float(max(max(state["base_force"] for state in reply) for reply in replies)),
             "mujoco": float(max(base_forces))}
    # The states from which MuJoCo's base tips past 90° within the horizon while still
    # within 45° of upright: does this engine tip from them too?
    onsets = []
    for s, reply in zip(starts, replies):
        if tilt_deg(qpos[s][3:7]) < 45.0 and max(tilt_deg(qpos[s + h][3:7]) for h in range(1, horizon + 1)) > 90.0:
            ours = max(tilt_deg(np.array(state["qpos"])[3:7]) for state in reply)
            onsets.append({"time": s * crawler.dt, "tilt_deg": tilt_deg(qpos[s][3:7]), "rapier_max_tilt_deg": ours})
    report = {
        "gait": gait,
        "start_deg": args.start,
        "lift": args.lift,
        "replays": len(starts),
        "horizon_steps": horizon,
        "mujoco_flips": crawler.flips,
        "mujoco_speed": float(qpos[steps][0] - qpos[0][0]) / args.seconds,
        "drift": {str(h): row for h, row in table.items()},
        "one_step_by_phase": by_phase,
        "base_contact": {"by_window_steps": {str(w): row for w, row in contact.items()}, "peak_force_n": peaks},
        "tip_onsets": {
            "count": len(onsets),
            "rapier_tips_too": sum(o["rapier_max_tilt_deg"] > 90.0 for o in onsets),
            "rapier_max_tilt_deg_median": float(np.median([o["rapier_max_tilt_deg"] for o in onsets])) if onsets else None,
        },
    }
    json.dump(report, sys.stdout)
    print()
    print(f"{len(starts)} replays of {horizon} steps from MuJoCo's trajectory "
          f"({report['mujoco_speed']:.3f} m/s, {crawler.flips} flips there):", file=sys.stderr)
    for h, row in table.items():
        cells = ", ".join(f"{name} {row[name]['mean_abs']:.3g} ({row[name]['mean']:+.3g})" for name in measures)
        ratio = "n/a" if row["progress_ratio"] is None else f"{row['progress_ratio']:.3f}"
        print(f"  after {h} steps, mean |rapier − MuJoCo| (mean signed): {cells}; base progress here / "
              f"there {ratio}", file=sys.stderr)
    for phase, row in by_phase.items():
        print(f"  one step from {row['replays']} states '{phase}': mean |Δ| pitch rate {row['pitch_rate']:.3g}, "
              f"q1 rate {row['q1_rate']:.3g}, q2 rate {row['q2_rate']:.3g} rad/s", file=sys.stderr)
    for window, row in contact.items():
        normal, landing = row["normal_impulse_ns"], row["landing_impulse_ns"]
        print(f"  base contact over {window} steps from each state, summed over the replays: normal impulse "
              f"{normal['rapier']:.3g} N·s here, {normal['mujoco']:.3g} in MuJoCo; landing impulse (> "
              f"{BASE_IMPACT_THRESHOLD:g} N) {landing['rapier']:.3g} here, {landing['mujoco']:.3g} in MuJoCo; "
              f"MuJoCo lands in {row['replays_landing_in_mujoco']} replays, this engine in "
              f"{row['of_those_landing_here']} of those and {row['replays_landing_here']} in all", file=sys.stderr)
    print(f"  peak base force: {peaks['rapier']:.4g} N here, {peaks['mujoco']:.4g} N in MuJoCo", file=sys.stderr)
    tips = report["tip_onsets"]
    print(f"  MuJoCo tips past 90° from {tips['count']} of the states (≤ 45° at the start); this engine from "
          f"{tips['rapier_tips_too']} of them (median largest tilt {tips['rapier_max_tilt_deg_median']})",
          file=sys.stderr)


def observe(args) -> None:
    crawler = Crawler()
    crawler.reset(args.q1, args.q2)
    torques = np.array(args.torques if args.steps > 0 else [0.0, 0.0])
    for _ in range(args.steps):
        crawler.step(torques)
    print(json.dumps([float(v) for v in crawler.observe(torques)]))


def side_tilt_deg(rotation: np.ndarray) -> float:
    """How far the base's side axis (y, the hinges' axis) tips out of the horizontal, in
    degrees: a roll onto a side. Unlike an Euler roll it stays 0 when the base pitches over."""
    return math.degrees(math.asin(max(-1.0, min(1.0, float(rotation[2, 1])))))


def solvers(args) -> None:
    gait = gait_from_args(args.gait)
    variants = {
        "pgs (the model's)": {},
        "newton": {"solver": mujoco.mjtSolver.mjSOL_NEWTON},
        "cg": {"solver": mujoco.mjtSolver.mjSOL_CG},
        "pgs, elliptic cones": {"cone": mujoco.mjtCone.mjCONE_ELLIPTIC},
    }
    for name, options in variants.items():
        crawler = Crawler()
        for key, value in options.items():
            setattr(crawler.model.opt, key, value)
        crawler.reset(args.start[0] * DEG, args.start[1] * DEG)
        tilts = []
        for s in range(round(args.seconds / crawler.dt)):
            crawler.step(square_wave(gait, s * crawler.dt))
            tilts.append(abs(side_tilt_deg(crawler.rotation())))
        after_1s = tilts[min(round(1.0 / crawler.dt), len(tilts)) - 1]
        print(json.dumps({
            "solver": name,
            "speed": crawler.distance(1.0) / args.seconds,
            "flips": crawler.flips,
            "max_side_tilt_deg": max(tilts),
            "mean_side_tilt_deg": float(np.mean(tilts)),
            "side_tilt_after_1s_deg": after_1s,
        }))


def airborne_states(count: int, seed: int) -> list:
    """Random states of the crawler high in the air: poses over both joints' ranges, planar
    velocities (the gaits' plane), and random torques."""
    rng = np.random.default_rng(seed)
    states = []
    for _ in range(count):
        q1, q2 = rng.uniform(-1.3, 1.3), rng.uniform(0.05, 2.5)
        velocity = rng.normal(0.0, 8.0, 5) * [0.1, 0.1, 1.0, 1.0, 1.0]
        states.append((q1, q2, velocity, rng.uniform(-1.0, 1.0, 2)))
    return states


def run_state_replay(binary: str, overrides: list, queries: str, expected: int) -> list:
    """This engine's answers (each a list of states) to `expected` state_replay queries, the
    JSON lines `queries`, with the env settings `overrides`; exits naming the failure."""
    result = subprocess.run([binary, *overrides], input=queries, capture_output=True, text=True)
    if result.returncode != 0:
        sys.exit(f"error: {binary} failed ({result.returncode}): {result.stderr.strip()}")
    replies = [json.loads(line)["states"] for line in result.stdout.splitlines() if line.strip()]
    if len(replies) != expected:
        sys.exit(f"error: {binary} answered {len(replies)} of {expected} queries")
    return replies


def one_step(crawler: Crawler, state) -> tuple:
    """qpos and qvel before, and qvel after, one step of `crawler` from an airborne `state`."""
    q1, q2, velocity, torques = state
    crawler.reset(q1, q2)
    crawler.data.qpos[2] += 0.5
    crawler.data.qvel[:] = 0.0
    crawler.data.qvel[[0, 2, 4, 6, 7]] = velocity
    mujoco.mj_forward(crawler.model, crawler.data)
    qpos, qvel = crawler.data.qpos.copy(), crawler.data.qvel.copy()
    crawler.step(torques)
    return qpos, qvel, crawler.data.qvel.copy()


def pair(args) -> None:
    """What the MJCF's base–link 1 contact pair does to the shoulder in one step, fitted as a
    soft constraint on its rate (`d·a_ref + (1 − d)·a₀`, `a_ref = −B·q̇1`, d = d0 + d1·cos q1),
    and, with --rapier, how far this engine's one step lands from MuJoCo's on other states."""
    with_pair, without_pair = Crawler(), Crawler(without_shoulder_pair=True)
    features, effects = [], []
    for state in airborne_states(args.states, args.seed):
        _, before, after = one_step(with_pair, state)
        _, _, free = one_step(without_pair, state)
        free_change, cosine = free[6] - before[6], math.cos(state[0])
        rate_dt = before[6] * with_pair.dt
        features.append([free_change, free_change * cosine, rate_dt, rate_dt * cosine])
        effects.append(after[6] - free[6])
    features, effects = np.array(features), np.array(effects)
    coefficients, *_ = np.linalg.lstsq(features, effects, rcond=None)
    residual = effects - features @ coefficients
    r_squared = 1.0 - float((residual**2).sum() / ((effects - effects.mean()) ** 2).sum())
    d0, d1 = -coefficients[0], -coefficients[1]
    # d·B = −(coefficients[2] + coefficients[3]·cos q1); B from the level link's values.
    damping = float((coefficients[2] + coefficients[3]) / (coefficients[0] + coefficients[1]))
    result = {"states": args.states, "d0": float(d0), "d1": float(d1), "B": damping, "r_squared": r_squared}
    summary = f"MuJoCo's pair: d = {d0:.4f} + {d1:.4f}·cos q1, B = {damping:.1f} /s (R² = {r_squared:.4f}, {args.states} states)"
    if args.rapier:
        checked = airborne_states(args.states, args.seed + 1)
        queries, theirs, free_ones = [], [], []
        for state in checked:
            qpos, qvel, after = one_step(with_pair, state)
            free_ones.append(one_step(without_pair, state)[2])
            theirs.append(after)
            query = {"qpos": [float(v) for v in qpos], "qvel": [float(v) for v in qvel],
                     "torques": [[float(t) for t in state[3]]]}
            queries.append(json.dumps(query) + "\n")
        replies = run_state_replay(args.rapier, args.overrides, "".join(queries), len(checked))
        ours = [np.array(states[0]["qvel"]) for states in replies]
        rates = [4, 6, 7]
        error = np.mean([np.abs(o[rates] - t[rates]) for o, t in zip(ours, theirs)], axis=0)
        unpaired = np.mean([np.abs(f[rates] - t[rates]) for f, t in zip(free_ones, theirs)], axis=0)
        result["one_step_error"] = {"rapier": error.tolist(), "mujoco_without_the_pair": unpaired.tolist()}
        summary += (
            f"\none step from {len(checked)} other states, mean |Δ| pitch / q1 / q2 rate against MuJoCo with the"
            f" pair: this engine {error[0]:.3f} / {error[1]:.3f} / {error[2]:.3f} rad/s, MuJoCo without it"
            f" {unpaired[0]:.3f} / {unpaired[1]:.3f} / {unpaired[2]:.3f}"
        )
    print(json.dumps(result))
    print(summary, file=sys.stderr)


def gait_from_args(values) -> dict:
    """The square wave of a --gait PERIOD HIGH1 HIGH2 LOW1 LOW2 LAG argument."""
    period, high1, high2, low1, low2, lag = values
    return {"period": period, "high": [high1, high2], "low": [low1, low2], "phase_lag": lag}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    eval_parser = commands.add_parser("eval", help="greedy episodes of a checkpoint in MuJoCo")
    eval_parser.add_argument("checkpoints", help="a run's checkpoints directory or one step-* directory")
    eval_parser.add_argument("--episodes", type=int, default=10)
    eval_parser.add_argument("--seconds", type=float, default=20.0)
    eval_parser.add_argument("--seed", type=int, default=1_000_000)
    eval_parser.add_argument("--action-repeat", type=int, help="override the checkpoint's action repeat")
    eval_parser.set_defaults(run=evaluate)
    scan_parser = commands.add_parser("scan", help="every kept checkpoint of a run in MuJoCo")
    scan_parser.add_argument("checkpoints", help="a run's checkpoints directory")
    scan_parser.add_argument("--episodes", type=int, default=10)
    scan_parser.add_argument("--seconds", type=float, default=20.0)
    scan_parser.add_argument(
        "--seed", type=int, default=2_000_000,
        help="start poses' seed; not eval's, so a checkpoint chosen here is confirmed on other starts",
    )
    scan_parser.add_argument("--every", type=int, default=1, help="play every n-th step-* checkpoint")
    scan_parser.add_argument("--top", type=int, default=10, help="upright checkpoints listed on stderr")
    scan_parser.set_defaults(run=scan)
    act_parser = commands.add_parser("act", help="greedy actions for observations on stdin")
    act_parser.add_argument("checkpoints")
    act_parser.set_defaults(run=act)
    observe_parser = commands.add_parser("observe", help="the observation after a reset, as JSON")
    observe_parser.add_argument("q1", type=float)
    observe_parser.add_argument("q2", type=float)
    observe_parser.add_argument("--steps", type=int, default=0)
    observe_parser.add_argument("--torques", type=float, nargs=2, default=[0.0, 0.0])
    observe_parser.set_defaults(run=observe)
    gait_parser = commands.add_parser("gaits", help="the gait bank from stdin, in MuJoCo")
    gait_parser.set_defaults(run=gaits)
    replay_parser = commands.add_parser("replay", help="sim-to-sim state replay along a MuJoCo trajectory")
    replay_parser.add_argument("--rapier", required=True, help="the state_replay example's binary")
    replay_parser.add_argument(
        "--gait", type=float, nargs=6, default=[0.3, -1.0, 1.0, 0.0, -1.0, 0.0],
        metavar=("PERIOD", "HIGH1", "HIGH2", "LOW1", "LOW2", "LAG"),
        help="the square wave (default: the issue's tumbling gait, 0.3 s, τ1 −1/0, τ2 +1/−1)",
    )
    replay_parser.add_argument("--checkpoint", help="replay this policy's MuJoCo trajectory instead of a gait")
    replay_parser.add_argument("--start", type=float, nargs=2, default=[-22.5, 11.25], metavar=("Q1_DEG", "Q2_DEG"))
    replay_parser.add_argument("--seconds", type=float, default=5.0)
    replay_parser.add_argument("--every", type=int, default=5, help="replay from every n-th physics step")
    replay_parser.add_argument("--horizon", type=int, default=50, help="physics steps per replay")
    replay_parser.add_argument("--lift", type=float, default=0.0, help="start this high in the air (m): no contacts")
    replay_parser.add_argument("overrides", nargs="*", help="env settings KEY=VALUE for this engine")
    replay_parser.set_defaults(run=replay)
    pair_parser = commands.add_parser("pair", help="the base–link 1 contact pair's effect on the shoulder, fitted")
    pair_parser.add_argument("--rapier", help="the state_replay example's binary: also this engine's one-step error")
    pair_parser.add_argument("--states", type=int, default=400, help="random airborne states to fit on")
    pair_parser.add_argument("--seed", type=int, default=0)
    pair_parser.add_argument("overrides", nargs="*", help="env settings KEY=VALUE for this engine")
    pair_parser.set_defaults(run=pair)
    solvers_parser = commands.add_parser("solvers", help="a square wave under each of MuJoCo's solvers: rolls")
    solvers_parser.add_argument(
        "--gait", type=float, nargs=6, default=[0.3, -1.0, 1.0, 0.0, -1.0, 0.0],
        metavar=("PERIOD", "HIGH1", "HIGH2", "LOW1", "LOW2", "LAG"),
        help="the square wave (default: the issue's tumbling gait)",
    )
    solvers_parser.add_argument("--start", type=float, nargs=2, default=[-22.5, 11.25], metavar=("Q1_DEG", "Q2_DEG"))
    solvers_parser.add_argument("--seconds", type=float, default=10.0)
    solvers_parser.set_defaults(run=solvers)
    args = parser.parse_args()
    args.run(args)


if __name__ == "__main__":
    main()
