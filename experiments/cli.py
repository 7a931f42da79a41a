"""The command line of the demos and benchmarks: `python sim.py [DEMO] [flags]` (sim.py's entry calls main). Each
demo accepts only the flags it uses; `python sim.py DEMO --help` lists them."""
from __future__ import annotations

import importlib
import json
import sys

import checks
from sim import PRESETS

SEEDS = "0..4294967295"                                # NumPy's 32-bit seed range (any seed >= 0 works; kept printable)

# name: (help, "module:function", flags). The module is imported only when its demo runs.
DEMOS = {
    "static": ("(default) CPIC holds a pose, an unknown payload arrives, RME detects, estimates, compensates",
               "experiments.scenarios:static_hold", ("preset", "seed", "plot", "view")),
    "basket": ("sequential loads added and removed with human pushes in between",
               "experiments.scenarios:basket", ("preset", "seed", "plot", "view")),
    "limit-cycle": ("CPIC tracking a y-z limit cycle, a payload added, without and with RME",
                    "experiments.scenarios:limit_cycle", ("preset", "seed", "plot", "view")),
    "pick-place": ("move, grasp, carry (+0.5 kg mid-carry), place", "experiments.scenarios:pick_place",
                   ("preset", "seed", "plot", "view")),
    "hold": ("CPIC static hold, payload at 1.75 s, without and with exact compensation", "experiments.demos:hold",
             ("preset", "seed", "plot", "view")),
    "payload": ("measured tau_ext beside payload_torque for the true payload", "experiments.demos:payload",
                ("preset", "seed", "view")),
    "hidden-effect": ("a log with a hidden physical effect: compare, diagnose, add it, watch the error fall",
                      "experiments.demos:hidden_effect", ("preset", "seed", "plot", "view", "json")),
    "better-model": ("fit the robot's friction from a log, give it to RME, compare the estimates",
                     "experiments.scenarios:better_model", ("seed",)),
    "bench": ("the paper's Tables 1, 4, 5 in simulation (about 5 minutes)", "experiments.bench:bench",
              ("seed", "calibration", "json")),
    "timing": ("median microseconds of every hot path", "experiments.cli:_timing", ("json",)),
    "detector-bench": ("Algorithm 1 as printed alone: latency, misses, false detections, time per update",
                       "experiments.cli:_detector_bench", ("seed", "json")),
    "vi-bench": ("VI alone on simulated windows: time, iterations, error, coverage", "experiments.cli:_vi_bench",
                 ("seed", "json")),
    "qp-bench": ("the QP solver against quadprog on random problems (needs quadprog, a test-only package)",
                 "experiments.cli:_qp_bench", ("seed", "json")),
    "reliability": ("randomised loads, swaps, removals and pushes on random poses, tuning or test episodes: "
                    "changes compensated, how soon, pushes left alone", "experiments.reliability:main",
                    ("split", "plant", "episodes", "first", "jobs", "estimator", "calibration", "json")),
    "calibration": ("coverage and sharpness of RME's 2-sigma intervals on the realistic preset, rest-window spread",
                    "experiments.calibration:main", ("seed", "calibration", "json", "windows")),
    "real-logs": ("real robot logs of one unchanged load: RME beside least squares and the range rule, per rest window",
                  "experiments.real_logs:main", ("dir", "calibration", "leave_pose_out", "pose_model", "mass",
                                                    "json")),
    "diagnose-bench": ("the diagnosis tool on a 20,000-sample, 7-joint log: wall time",
                       "experiments.cli:_diagnose_bench", ("json",)),
    "explore": ("Table 5's payloads: a small tilt makes the CoM along gravity observable, before and after",
                "experiments.explore_demo:explore", ("seed", "json")),
    "identify-bench": ("the tool on the flange identified from its motion: random tools, errors beside the targets",
                       "experiments.tool_bench:identify_bench", ("preset", "seed", "json", "tools")),
    "inertia": ("the payload's inertia from motion and its compensation on a wrist-turning limit cycle (about 1 min)",
                "experiments.inertia_demo:inertia_demo", ("seed", "json")),
}

FLAGS = {
    "preset": (("--preset",), dict(default="realistic", choices=("ideal", "realistic"), help="plant and sensors")),
    "seed": (("--seed",), dict(type=checks.argument(SEEDS), default=0,
                               help=f"seed of the np.random.Generator, {SEEDS}")),
    "plot": (("--plot",), dict(metavar="FILE", type=checks.writable, default=None,
                               help="save a figure (needs matplotlib; its folder must exist)")),
    "view": (("--view",), dict(action="store_true", help="open MuJoCo's viewer when a display exists")),
    "json": (("--json",), dict(action="store_true", help="print the results as one JSON object")),
    "episodes": (("--episodes",), dict(type=checks.argument("1..100000"), default=20,
                                       help="episodes of each kind, 1..100000")),
    "first": (("--first",), dict(type=checks.argument("0..1000000"), default=0,
                                 help="index of the first episode (default 0): a fresh block for a design already "
                                      "judged on the ones before")),
    "split": (("--split",), dict(default="tuning", choices=("tuning", "test"),
                                 help="episode seeds: tuning (default) or test (only to judge a finished estimator)")),
    "plant": (("--plant",), dict(default="realistic", choices=PRESETS, help="plant and sensors")),
    "jobs": (("--jobs",), dict(type=checks.argument("1..64"), default=1, help="worker processes, 1..64")),
    "estimator": (("--estimator",), dict(metavar="MODULE:CLASS", default="rme:RME",
                                         help="the estimator, built as CLASS(robot, rng=...) (default rme:RME)")),
    "windows": (("--windows",), dict(type=checks.argument("1..1000000"), default=200,
                                     help="simulated windows, 1..1000000")),
    "dir": (("dir",), dict(metavar="DIR", help="a folder of libfranka-style CSV or franka.py .npz logs")),
    "calibration": (("--calibration",), dict(metavar="FILE", default=None,
                                             help="RME's error model (python rme.py calibrate LOG --save FILE)")),
    "leave_pose_out": (("--leave-pose-out",), dict(action="store_true",
                                                   help="also RME calibrated, per pose, on the other poses' windows")),
    "pose_model": (("--pose-model",), dict(default="offset", choices=("offset", "links"),
                                           help="--leave-pose-out's calibration: the pose error as an offset and a "
                                                "covariance (default) or as the links' inertial errors")),
    "mass": (("--mass",), dict(type=checks.argument("(0, 50]"), default=None, metavar="KG",
                               help="the load's mass known otherwise: how often each interval holds it")),
    "tools": (("--tools",), dict(type=checks.argument("1..1000"), default=5, help="random tools, 1..1000")),
}


def parser() -> checks.Parser:
    p = checks.Parser(prog="sim.py", description="MuJoCo Panda demos and benchmarks for Rapid Mismatch "
                                "Estimation. With no DEMO: static.")
    sub = p.add_subparsers(dest="demo", metavar="DEMO")
    for name, (text, _, flags) in DEMOS.items():
        d = sub.add_parser(name, help=text, description=text)
        for f in flags:
            args, kwargs = FLAGS[f]
            d.add_argument(*args, **kwargs)
    return p


def main(argv=None) -> int:
    argv = list(argv or [])
    if not argv or (argv[0].startswith("-") and argv[0] not in ("-h", "--help")):
        argv = ["static"] + argv                       # the main demo is the default
    p = parser()
    args = p.parse_args(argv)
    if getattr(args, "plot", None):
        try:
            import matplotlib  # noqa: F401
        except ImportError:                        # one line, no usage: the command itself was right
            p.exit(2, "sim.py: --plot needs matplotlib, which is not installed (pip install matplotlib)\n")
    module, function = DEMOS[args.demo][1].split(":")
    try:
        getattr(importlib.import_module(module), function)(args)
    except (ValueError, RuntimeError, OSError) as err:   # a failure is one line on stderr, no traceback
        print(f"sim.py {args.demo}: {type(err).__name__}: {err}", file=sys.stderr)
        return 1
    return 0


def _print(args, title, result):
    if args.json:
        print(json.dumps(result))
    else:
        from experiments.timing import print_dict
        print_dict(title, result)


def _timing(args):
    from experiments.timing import timing
    rows = timing(table=not args.json)
    if args.json:
        print(json.dumps(rows))


def _detector_bench(args):
    from experiments.timing import detector_benchmark
    r = detector_benchmark(seed=args.seed)
    if args.json:
        return print(json.dumps(r))
    from experiments.timing_tools import print_table
    ms = lambda v: f"{v:.0f}"
    print_table(f"Algorithm 1 as printed (realistic plant, seed {args.seed}): payloads added at 1.0 s, removed at "
                "2.5 s",
                ["changes", "detected", "missed", "extra detections", "latency median [ms]", "p90 [ms]", "max [ms]"],
                [[r["events"], r["detected"], r["missed"], r["extra_detections"], ms(r["latency_ms_median"]),
                  ms(r["latency_ms_p90"]), ms(r["latency_ms_max"])]],
                "latency: from the change to its detection (within 0.5 s, else missed); extra: detections that "
                "answer no change.")
    f = r["false_detections"]
    print_table("\nfalse detections (totals over 3 plants, no payload change)", ["episode", "detections"],
                [[label, f[key]] for label, key in (("lateral pushes, 7 s", "pushes_7s"),
                                                    ("free motion, 5 s", "motion_5s"), ("rest, 5 s", "rest_5s"))],
                "each count is a detection where nothing was added or removed: fewer is better.")
    u = r["update_us_median"]
    print_table("\ntime per update [us], median", ["buffer", "force given", "J given"],
                [[f"{w} samples", f"{u[f'window {w}, force given']:.1f}", f"{u[f'window {w}, J given']:.1f}"]
                 for w in (500, 50_000)],
                "O(1) per sample: the same time for a 100x longer buffer; the 1 kHz loop has 1000 us per cycle.")


def _vi_bench(args):
    from experiments.timing import vi_benchmark
    r = vi_benchmark(seed=args.seed)
    if args.json:
        return print(json.dumps(r))
    from experiments.timing_tools import print_table
    f = lambda v, k=2: f"{v:.{k}f}"
    rows = [[name, f(v["ms_median"]), f(v["ms_p90"]), f"{v['iterations_median']:.0f} / {v['iterations_max']}",
             f"{100 * v['converged']:.0f}", f(v["rmse"][0], 3), " ".join(f"{1e3 * x:.0f}" for x in v["rmse"][1:]),
             " ".join(f"{100 * x:.0f}" for x in v["cover2_marginal"]), " ".join(f"{100 * x:.0f}" for x in
                                                                             v["cover2_std"])]
            for name, v in r.items()]
    print_table(f"VI benchmark (realistic simulated windows: Table 5's payloads and random ones, seed {args.seed})",
                ["start, prior mean", "time median [ms]", "p90 [ms]", "iterations median / max", "converged [%]",
                 "RMSE m [kg]", "rx ry rz [mm]", "in 2 std [%] m rx ry rz", "in 2 mean-field std [%]"], rows,
                "coverage: the share of windows whose truth lies within 2 std of the estimate (about 95 % if the "
                "std is right); rz from the prior where the pose does not observe it.")


def _diagnose_bench(args):
    from experiments.timing import diagnose_benchmark
    r = diagnose_benchmark()
    if args.json:
        return print(json.dumps(r))
    from experiments.timing_tools import print_table
    print_table("diagnose benchmark (a synthetic multi-sine log with Gaz friction and offsets)",
                ["samples", "joints", "loading and filtering [s]", f"diagnose, median of {r['runs']} [s]",
                 "effects selected"], [[r["samples"], r["joints"], f"{r['prepare_s']:.2f}", f"{r['median_s']:.2f}",
                                        ", ".join(r["selected"]) or "none"]],
                "the wall time of one diagnosis of a 20 s log at 1 kHz; it should select the hidden effects.")


def _qp_bench(args):
    from experiments.qp_bench import qp_benchmark
    try:
        res = qp_benchmark(seed=args.seed, show=not args.json)
    except ModuleNotFoundError as err:
        if err.name != "quadprog":
            raise
        raise SystemExit("qp-bench compares with quadprog, which is not installed (pip install quadprog)")
    if args.json:
        print(json.dumps(res))
