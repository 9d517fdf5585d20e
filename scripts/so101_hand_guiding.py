"""Hand guiding of the SO-101, measured on the emulated arm (issue 36, item 5):

- the force at the gripper that moves it 1 cm within 1 s, a Cartesian force on the
  gripper's body through every joint at once (`SimulatedServos.set_external_force`:
  sim-servo's `push-force`), per direction of the base frame at home: the servos
  holding (position control), gravity compensation (K6 = 0), a compliant hold;
- the breakaway force under gravity compensation: a slow force ramp at the gripper,
  the force when the gripper has moved 1 mm;
- a compliant hold with a chosen joint stiffness (`controller.stiffness`, N·m/rad):
  the stiffness realized, ± a torque on every joint at once, at steady state.

Every run is the fused controller of `hrp2-drake control --motion hold` on the
emulated servos in one process with the bus loop's timing
(`run_on_bus_in_process`: lock step's physics and timing, call for call); the
controller reads only the servos' encoders. The gripper's true position and the
true joint angles (ground truth) are read for evaluation only, and every
displacement is against the same run without the push (the hold's own sag and
drift taken out). It writes hand_guiding.md, hand_guiding.json and
hand_guiding.png in --out.

    python scripts/so101_hand_guiding.py --motor-model MODEL.yaml --out DIR [--quick]

MODEL.yaml: the identified motor model (docs/feetech.md: record at P 16 and 32,
then identify --fit least-squares), used at the servos' P 32 as `control` does.
"""

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hrp2_drake.assembly.robot_control import load_on_robot
from hrp2_drake.control.fused import FusedController
from hrp2_drake.description import load_robot_description
from hrp2_drake.hardware.in_process import run_on_bus_in_process
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.report import markdown_table, pyplot, save_figure
from hrp2_drake.robot.ground_truth import true_motor_model
from hrp2_drake.robot.station import StationConfig
from hrp2_drake.tools.control import (
    ControlConfig,
    at_robot_gain,
    control_chain_parts,
    control_reference,
)

ROBOT = "so101"
BODY = "gripper_frame_link"  # the gripper's frame (the URDF's)
DIRECTIONS = {
    "+x": (1, 0, 0),
    "-x": (-1, 0, 0),
    "+y": (0, 1, 0),
    "-y": (0, -1, 0),
    "+z": (0, 0, 1),
    "-z": (0, 0, -1),
}
PUSH = 1.5  # s: the push starts (torque control from 0.5 s, its ramp over)
MOVE, WINDOW = 0.01, 1.0  # 1 cm within 1 s
BREAKAWAY = 0.001  # m: the gripper has broken away when it has moved 1 mm
MAX_FORCE = 64.0  # N: the largest force tried
#: The emulated servo (`StationConfig.servo_file`; --servo-file): empty, the arm's
#: servo.yaml (BAM's STS3215); another file only to find a result's cause.
SERVO_FILE = ""


@dataclass
class Hold:
    """How the arm holds home: the servos alone (position control: the chain never
    leaves it), or torque control with K6 or a joint stiffness (N·m/rad)."""

    name: str
    k6: float | None = None
    stiffness: float | None = None

    @property
    def torque(self) -> bool:
        return self.k6 is not None or self.stiffness is not None

    def controller(self, model: MotorModel, duration: float):
        """The fused controller of `control --motion hold` (the arm's control.yaml)
        and its reference."""
        config, _ = load_on_robot(ControlConfig, load_robot_description(ROBOT))
        config.robot, config.motion, config.duration = ROBOT, "hold", duration
        torque = config.torque_control
        torque.controller.k6 = self.k6 or 0.0
        if self.stiffness is not None:
            torque.controller.stiffness = [self.stiffness]
        if not self.torque:
            torque.start_time = duration + 1.0  # position control throughout
        reference = control_reference(config)
        robot = config.description()
        model = at_robot_gain(model, robot)  # as control
        parts = control_chain_parts(config, model, reference)
        return FusedController(parts), reference


def run(hold: Hold, model: MotorModel, duration: float, force=None, torque=None):
    """One closed-loop run: `force(t)` (N, world) on the gripper, `torque(t)` (N·m)
    on every joint, each held over a period. Returns t, the gripper's true position
    p, the true joint angles q and torque control's share α, per period."""
    controller, reference = hold.controller(model, duration)
    period = controller.parts.period
    log = {"t": [], "p": [], "q": [], "alpha": []}

    def on_period(servos, t):
        if force is not None:
            servos.set_external_force(BODY, force(t))
        if torque is not None:
            servos.set_external_torque(torque(t))
        log["t"].append(t)
        log["p"].append(servos.body_position(BODY))
        log["q"].append(servos.joint_positions())
        log["alpha"].append(controller.torque_active())

    ticks = int(round(duration / period)) + 1
    station = StationConfig(robot=ROBOT, scenario="fixed_base", servo_file=SERVO_FILE)
    run_on_bus_in_process(station, controller, reference, ticks, on_period=on_period)
    return {name: np.array(values) for name, values in log.items()}


def constant(value, start: float = PUSH):
    """A push of `value` from `start` on (zero before)."""
    value = np.asarray(value, dtype=float)
    return lambda t: value if t >= start else 0.0 * value


def moved(result: dict, base: dict) -> np.ndarray:
    """The gripper's displacement from the push on (m, per period): its distance
    from where the run without the push has it at the same time."""
    return np.linalg.norm(result["p"] - base["p"], axis=1)


def force_to_move(hold: Hold, model, direction, base: dict, iterations: int):
    """The smallest constant force (N) along `direction` from PUSH on that moves the
    gripper MOVE within WINDOW (bisection, to 1/2**iterations of its bracket), and
    the displacement's angle to the push there (deg); inf beyond MAX_FORCE."""
    duration = PUSH + WINDOW
    d = np.asarray(direction, dtype=float)

    def push(force):
        result = run(hold, model, duration, force=constant(force * d))
        return moved(result, base).max(), result

    low, high = 0.0, 0.5
    reach, result = push(high)
    while reach < MOVE:
        if high >= MAX_FORCE:
            return np.inf, np.nan
        low, high = high, 2 * high
        reach, result = push(high)
    for _ in range(iterations):
        middle = 0.5 * (low + high)
        reach, trial = push(middle)
        if reach >= MOVE:
            high, result = middle, trial
        else:
            low = middle
    delta = result["p"][-1] - base["p"][-1]
    angle = np.degrees(np.arccos(np.clip(delta @ d / np.linalg.norm(delta), -1, 1)))
    return high, float(angle)


def breakaway(model, direction, base: dict, rate: float, peak: float):
    """Under gravity compensation, a force ramp of `rate` N/s along `direction`
    from PUSH up to `peak` N: the force when the gripper has moved BREAKAWAY (N;
    inf if it never has), and the run."""
    d = np.asarray(direction, dtype=float)
    duration = PUSH + peak / rate
    result = run(
        Hold("K6 = 0", k6=0.0),
        model,
        duration,
        force=lambda t: max(0.0, rate * (t - PUSH)) * d,
    )
    gone = np.flatnonzero(moved(result, base) >= BREAKAWAY)
    force = rate * (result["t"][gone[0]] - PUSH) if len(gone) else np.inf
    return force, result


def stiffness_realized(model, stiffness: float, displacement: float = 0.1):
    """A compliant hold at `stiffness` (N·m/rad, every joint): ±τ0 = ±stiffness ×
    `displacement` on every joint at once from PUSH on, until steady state (8 time
    constants of the servo's slowest damping at rest, 1.7 N·m·s/rad, at least 3 s).
    The stiffness realized per joint, 2 τ0 / (q₊ − q₋) over the last 0.5 s, and
    how much q₊ − q₋ still changed over the 0.5 s before (its relative change)."""
    hold = Hold(f"stiffness {stiffness:g}", stiffness=stiffness)
    duration = PUSH + max(3.0, 8 * 1.7 / stiffness)
    tau = stiffness * displacement * np.ones(6)
    plus = run(hold, model, duration, torque=constant(tau))
    minus = run(hold, model, duration, torque=constant(-tau))
    spread = plus["q"] - minus["q"]
    t = plus["t"]
    last = spread[t >= duration - 0.5].mean(axis=0)
    before = spread[(t >= duration - 1.0) & (t < duration - 0.5)].mean(axis=0)
    alpha = min(plus["alpha"][t >= PUSH].min(), minus["alpha"][t >= PUSH].min())
    return 2 * tau / last, np.abs(last - before) / np.abs(last), alpha, plus, minus


def coulomb_force(direction) -> float:
    """Ground truth, for evaluation only: the smallest force along `direction` at the
    gripper (at home) whose joint torques Jᵀ F reach a servo's Coulomb friction on
    some joint (N): where a servo with true static friction would break away."""
    robot = load_robot_description(ROBOT)
    truth = true_motor_model(robot, robot.joints)
    friction = truth.k_c / truth.k_tau  # N·m
    plant = robot.make_plant(weld_base=True)
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, robot.home_positions())
    J = gripper_jacobian(plant, context)
    lever = np.abs(J.T @ np.asarray(direction, dtype=float))
    return float(np.min(friction[lever > 0] / lever[lever > 0]))


def gripper_jacobian(plant, context) -> np.ndarray:
    """The gripper origin's translational Jacobian in the world (3, nv)."""
    from pydrake.multibody.tree import JacobianWrtVariable

    frame = plant.GetBodyByName(BODY).body_frame()
    world = plant.world_frame()
    return plant.CalcJacobianTranslationalVelocity(
        context, JacobianWrtVariable.kV, frame, np.zeros(3), world, world
    )


HOLDS = (Hold("position control"), Hold("K6 = 0", k6=0.0), Hold("K6 = 0.1", k6=0.1))
STIFFNESSES = (0.5, 1.0, 2.0, 5.0)
RAMPS = (0.5, 0.1)  # N/s
RAMP_PEAK = 2.0  # N


def measure_forces(model, directions, iterations: int) -> dict:
    """The 1 cm force (N) and the displacement's angle to the push (deg) per hold
    and direction, and each hold's drift over the window without a push (m)."""
    out = {}
    for hold in HOLDS:
        base = run(hold, model, PUSH + WINDOW)
        start = np.searchsorted(base["t"], PUSH)
        rows = {"drift": float(np.linalg.norm(base["p"][-1] - base["p"][start]))}
        rows["alpha"] = float(base["alpha"][start:].min())
        for name in directions:
            force, angle = force_to_move(
                hold, model, DIRECTIONS[name], base, iterations
            )
            rows[name] = {"force": float(force), "angle": angle}
        out[hold.name] = rows
    return out


def measure_breakaway(model, directions, rates) -> tuple[dict, dict]:
    """The breakaway force (N) per ramp rate and direction under gravity
    compensation, with the Coulomb force (ground truth: `coulomb_force`); and the
    runs of the slowest ramp (for the figure)."""
    out, runs = {}, {}
    for rate in rates:
        base = run(Hold("K6 = 0", k6=0.0), model, PUSH + RAMP_PEAK / rate)
        for name in directions:
            force, result = breakaway(model, DIRECTIONS[name], base, rate, RAMP_PEAK)
            out.setdefault(name, {"coulomb": coulomb_force(DIRECTIONS[name])})
            out[name][f"{rate:g} N/s"] = float(force)
            if rate == min(rates):
                runs[name] = (result["t"], moved(result, base))
    return out, runs


def measure_offsets(model, stiffness: float, displacements) -> dict:
    """The stiffness error's cause: at `stiffness`, per displacement (rad) of the
    push, the torque the hold misses per joint, τ0 (1 − K / K_realized) (N·m): a
    constant torque, not a constant ratio, is a resolution, not a gain error."""
    out = {}
    for displacement in displacements:
        realized = stiffness_realized(model, stiffness, displacement)[0]
        tau = stiffness * displacement
        out[f"{displacement:g}"] = (tau * (1.0 - stiffness / realized)).tolist()
    return out


def measure_stiffness(model, stiffnesses) -> dict:
    """Per chosen stiffness: the realized one per joint, its still-changing part,
    torque control's smallest share, and the stiffness the identified K_τ predicts
    (K K_τ,identified / K_τ,true: ground truth, for evaluation)."""
    robot = load_robot_description(ROBOT)
    truth = true_motor_model(robot, robot.joints)
    identified = at_robot_gain(model, robot)
    ratio = np.asarray(identified.subset(robot.joints).k_tau) / truth.k_tau
    out = {}
    for k in stiffnesses:
        realized, changing, alpha, _, _ = stiffness_realized(model, k)
        out[f"{k:g}"] = {
            "realized": realized.tolist(),
            "predicted": (k * ratio).tolist(),
            "still_changing": changing.tolist(),
            "alpha": float(alpha),
        }
    return out


def markdown(summary: dict) -> str:
    """hand_guiding.md: the three tables (`summary` as `measure` returns it)."""
    forces, directions = summary["forces"], summary["directions"]
    lines = [
        "# SO-101 hand guiding (emulated arm, in process with lock step's timing)",
        "",
        f"Motor model: `{summary['motor_model']}`. Push at the gripper "
        f"(`{BODY}`, base frame, home pose) from {PUSH:g} s. Command: "
        f"`{summary['command']}`.",
        "",
        f"## The force that moves the gripper {MOVE * 100:g} cm within {WINDOW:g} s",
        "",
        "N (angle of the displacement to the push, deg); drift: the hold's own "
        "motion over the window without a push",
        "",
    ]
    rows = [
        [name, *(_force_cell(forces[name][d]) for d in directions)]
        + [f"{forces[name]['drift'] * 1e3:.2f} mm", f"{forces[name]['alpha']:.2f}"]
        for name in forces
    ]
    lines += markdown_table(["hold", *directions, "drift", "min α"], rows)
    lines += ["", "## Breakaway under gravity compensation (K6 = 0)", ""]
    lines += [
        f"The force when the gripper has moved {BREAKAWAY * 1e3:g} mm on a ramp "
        "from 0 (N); Coulomb: where Jᵀ F reaches a servo's Coulomb friction "
        "(ground truth).",
        "",
    ]
    breakaway = summary["breakaway"]
    rates = [key for key in breakaway[directions[0]] if key != "coulomb"]
    rows = [
        [
            d,
            *(f"{breakaway[d][r]:.3f}" for r in rates),
            f"{breakaway[d]['coulomb']:.3f}",
        ]
        for d in directions
    ]
    lines += markdown_table(
        ["direction", *(f"ramp {r}" for r in rates), "Coulomb"], rows
    )
    lines += _stiffness_lines(summary)
    return "\n".join(lines) + "\n"


def _stiffness_lines(summary: dict) -> list[str]:
    """hand_guiding.md's compliant-hold tables."""
    lines = []
    lines += ["", "## Compliant hold at a chosen joint stiffness", ""]
    lines += [
        "`controller.stiffness` K on every joint; ±τ0 = ±0.1 rad × K on every "
        "joint at once; realized 2τ0 / (q₊ − q₋) at steady state, N·m/rad, per "
        "joint (error %); predicted: K × K_τ,identified / K_τ,true (ground truth).",
        "",
    ]
    rows = []
    for k, result in summary["stiffness"].items():
        cells = [
            f"{r:.3f} ({(r / float(k) - 1) * 100:+.1f} %)" for r in result["realized"]
        ]
        predicted = ", ".join(
            f"{(p / float(k) - 1) * 100:+.1f}" for p in result["predicted"]
        )
        rows.append(
            [k, *cells, predicted, f"{max(result['still_changing']) * 100:.2f} %"]
        )
    joints = load_robot_description(ROBOT).joints
    lines += markdown_table(
        ["K", *joints, "predicted error %", "still changing (0.5 s)"], rows
    )
    if summary["offsets"]:
        lines += [
            "",
            "The torque the hold misses at K = 0.5, τ0 (1 − K / K_realized) "
            "(mN·m), per push:",
            "",
        ]
        rows = [
            [
                f"±{float(d) * 0.5 * 1e3:g} mN·m ({d} rad)",
                *(f"{x * 1e3:.1f}" for x in offsets),
            ]
            for d, offsets in summary["offsets"].items()
        ]
        lines += markdown_table(["push", *joints], rows)
    if summary["servo_file"]:
        lines += ["", f"Emulated servo: `{summary['servo_file']}` (not the arm's)."]
    return lines


def _force_cell(cell: dict) -> str:
    if not np.isfinite(cell["force"]):
        return f"> {MAX_FORCE:g}"
    return f"{cell['force']:.3f} ({cell['angle']:.0f}°)"


def plot(summary: dict, runs: dict, path: Path) -> None:
    """hand_guiding.png: the breakaway ramps' displacement against the force, and
    the realized stiffness against the chosen one per joint."""
    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    rate = min(summary["rates"])
    for name, (t, distance) in runs.items():
        left.plot(np.maximum(0.0, rate * (t - PUSH)), distance * 1e3, label=name)
    left.axhline(BREAKAWAY * 1e3, color="k", lw=0.8, ls="--")
    left.set(
        xlabel=f"force at the gripper (N, ramp {rate:g} N/s)",
        ylabel="gripper displacement (mm)",
        title="K6 = 0: a force ramp",
        ylim=(0, 10 * BREAKAWAY * 1e3),
    )
    left.legend(fontsize=8)
    first = [
        v
        for d in runs
        for k, v in summary["breakaway"][d].items()
        if k == f"{rate:g} N/s"
    ]
    if np.isfinite(first).any():
        left.set_xlim(0, 4 * np.nanmax(np.where(np.isfinite(first), first, np.nan)))
    chosen = [float(k) for k in summary["stiffness"]]
    realized = np.array([r["realized"] for r in summary["stiffness"].values()])
    joints = load_robot_description(ROBOT).joints
    for j, joint in enumerate(joints):
        right.plot(chosen, realized[:, j], "o-", ms=3, label=joint)
    right.plot(chosen, chosen, "k--", lw=0.8, label="chosen")
    right.set(
        xscale="log",
        yscale="log",
        xlabel="chosen stiffness (N·m/rad)",
        ylabel="realized (N·m/rad)",
        title="compliant hold",
    )
    right.legend(fontsize=7)
    save_figure(fig, path, tight=True)


def measure(model_path: str, quick: bool) -> tuple[dict, dict]:
    """The three measurements (fewer directions, values and steps with `quick`)."""
    model = MotorModel.load(model_path)
    directions = ["+x", "+z"] if quick else list(DIRECTIONS)
    rates = RAMPS[:1] if quick else RAMPS
    stiffnesses = (1.0, 5.0) if quick else STIFFNESSES
    breakaway, runs = measure_breakaway(model, directions, rates)
    summary = {
        "motor_model": model_path,
        "directions": directions,
        "rates": list(rates),
        "forces": measure_forces(model, directions, 3 if quick else 7),
        "breakaway": breakaway,
        "stiffness": measure_stiffness(model, stiffnesses),
        "offsets": {} if quick else measure_offsets(model, 0.5, (0.05, 0.1, 0.3)),
        "servo_file": SERVO_FILE,
    }
    return summary, runs


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--motor-model", required=True, help="MotorModel YAML")
    parser.add_argument("--out", default="out/so101/hand_guiding")
    parser.add_argument("--quick", action="store_true", help="2 directions, 2 values")
    parser.add_argument(
        "--servo-file",
        default="",
        help="another emulated servo (a copy of servo.yaml changed), only to find "
        "a result's cause",
    )
    args = parser.parse_args(argv)
    global SERVO_FILE
    SERVO_FILE = args.servo_file
    try:
        MotorModel.load(args.motor_model)
    except (OSError, ValueError) as error:
        print(f"so101_hand_guiding: {error}", file=sys.stderr)
        return 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary, runs = measure(args.motor_model, args.quick)
    summary["command"] = " ".join(
        ["python scripts/so101_hand_guiding.py", *sys.argv[1:]]
    )
    (out / "hand_guiding.json").write_text(json.dumps(summary, indent=1))
    (out / "hand_guiding.md").write_text(markdown(summary))
    plot(summary, runs, out / "hand_guiding.png")
    print(f"report: {out / 'hand_guiding.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
