"""The command line of the demos and benchmarks: `python sim.py [DEMO] [flags]` (sim.py's entry calls main). Each
demo accepts only the flags it uses; `python sim.py DEMO --help` lists them."""
from __future__ import annotations

import importlib
import json
import sys

import checks

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
              ("seed", "json")),
    "timing": ("median microseconds of every hot path", "experiments.cli:_timing", ("json",)),
    "detector-bench": ("the detector alone: latency, misses, false detections, time per update",
                       "experiments.cli:_detector_bench", ("seed", "json")),
    "vi-bench": ("VI alone on simulated windows: time, iterations, error, coverage", "experiments.cli:_vi_bench",
                 ("seed", "json")),
    "qp-bench": ("the QP solver against quadprog on random problems (needs quadprog, a test-only package)",
                 "experiments.cli:_qp_bench", ("seed", "json")),
    "reliability": ("randomised loads, removals and pushes on random poses: how many changes are compensated",
                    "experiments.reliability:main", ("seed", "json", "episodes")),
    "calibration": ("coverage and sharpness of RME's 2-sigma intervals on the realistic preset, rest-window spread",
                    "experiments.calibration:main", ("seed", "json", "windows")),
    "diagnose-bench": ("the diagnosis tool on a 20,000-sample, 7-joint log: wall time",
                       "experiments.cli:_diagnose_bench", ("json",)),
    "explore": ("Table 5's payloads: a small tilt makes the CoM along gravity observable, before and after",
                "experiments.explore_demo:explore", ("seed", "json")),
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
    "episodes": (("--episodes",), dict(type=checks.argument("1..100000"), default=100,
                                       help="episodes of each kind, 1..100000")),
    "windows": (("--windows",), dict(type=checks.argument("1..1000000"), default=200,
                                     help="simulated windows, 1..1000000")),
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
        except ImportError:
            p.error("--plot needs matplotlib, which is not installed (pip install matplotlib)")
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
    _print(args, "detector benchmark (realistic plant)", detector_benchmark(seed=args.seed))


def _vi_bench(args):
    from experiments.timing import vi_benchmark
    _print(args, "VI benchmark (realistic simulated windows)", vi_benchmark(seed=args.seed))


def _diagnose_bench(args):
    from experiments.timing import diagnose_benchmark
    _print(args, "diagnose benchmark", diagnose_benchmark())


def _qp_bench(args):
    from experiments.qp_bench import qp_benchmark
    res = qp_benchmark(seed=args.seed, show=not args.json)
    if args.json:
        print(json.dumps(res))
