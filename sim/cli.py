"""``tupa scenarios ...`` and ``tupa sim ...``: scenario files and the network model; also
registers ``tupa site ...`` (:mod:`sim.sites.cli`)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from sim.config import ENVIRONMENTS, QUEUEING_CHOICES
from sim.scenarios import FAMILIES, SITE_FAMILIES


def register(subparsers: argparse._SubParsersAction) -> None:
    scenarios = subparsers.add_parser(
        "scenarios", help="generate and inspect scenario files", allow_abbrev=False
    )
    scenarios_sub = scenarios.add_subparsers(dest="scenarios_command", required=True)
    generate = scenarios_sub.add_parser(
        "generate",
        allow_abbrev=False,
        help="draw a seeded set of scenarios (users' positions and loads) and write it as JSON",
    )
    generate.add_argument("--n", type=int, default=500, help="number of scenarios (default 500)")
    generate.add_argument(
        "--users", type=int, default=3, help="users per scenario, 1..300 (default 3)"
    )
    generate.add_argument(
        "--family",
        default="exponential",
        metavar="{" + ",".join((*FAMILIES, *SITE_FAMILIES)) + "}",
        help="users' layout family (default exponential, the paper's; mixture: each scenario "
        "one of the others; streets, squares, crowd: on a site only, users in its streets, its "
        "largest squares, or mostly within 20 m of one point)",
    )
    generate.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    generate.add_argument(
        "--total-load-mbps",
        type=float,
        default=40.0,
        help="sum of the users' offered loads in Mbit/s (default 40, the paper's Λ)",
    )
    generate.add_argument(
        "--environment",
        default="open",
        metavar="ENV",
        help=f"what stands on the ground, recorded in the file: {', '.join(ENVIRONMENTS)} "
        "(default open, the paper's) or site:PATH (a site directory: users on its walkable "
        "ground)",
    )
    generate.add_argument("--out", type=Path, required=True, help="output file (JSON)")
    generate.set_defaults(handler=_generate)

    sim = subparsers.add_parser("sim", help="run the network model", allow_abbrev=False)
    sim_sub = sim.add_subparsers(dest="sim_command", required=True)
    evaluate = sim_sub.add_parser(
        "evaluate",
        allow_abbrev=False,
        help="simulate given UAV positions (a tupa-cases/1 file) and write per-user metrics",
    )
    evaluate.add_argument("cases", type=Path, help="case file (tupa-cases/1 JSON)")
    evaluate.add_argument("--out", type=Path, required=True, help="output file (JSON)")
    evaluate.add_argument("--seed", type=int, default=0, help="fading seed (default 0)")
    evaluate.add_argument(
        "--expected", action="store_true", help="deterministic expected mode (no fading draws)"
    )
    evaluate.add_argument("--queueing", choices=QUEUEING_CHOICES, default="fq-codel")
    evaluate.add_argument(
        "--backend",
        choices=("fast", "ns3"),
        default="fast",
        help="fast: the embedded model (default); ns3: ns-3 3.44 (pip install 'tupa[ns3]')",
    )
    evaluate.add_argument("--warmup-s", type=float, default=0.5, help="warm-up (default 0.5 s)")
    evaluate.add_argument(
        "--measure-s", type=float, default=2.0, help="measurement window (default 2 s)"
    )
    evaluate.set_defaults(handler=_evaluate)

    from sim.sites.cli import register as register_site  # tupa site: numpy-only until it runs

    register_site(subparsers)


def _generate(args: argparse.Namespace) -> int:
    from sim.channel import area_site
    from sim.config import AreaConfig, check_environment
    from sim.errors import InputError
    from sim.files import save_scenarios
    from sim.scenarios import (
        MAX_USERS,
        check_family_area,
        format_heterogeneity_histogram,
        generate_scenarios,
    )

    if args.n < 1:
        raise InputError(f"--n: must be at least 1, got {args.n}")
    if not 1 <= args.users <= MAX_USERS:
        raise InputError(f"--users: must be in 1..{MAX_USERS}, got {args.users}")
    if args.family not in (*FAMILIES, *SITE_FAMILIES):
        raise InputError(
            f"--family: unknown family {args.family!r} (choose from {', '.join(FAMILIES)}; on a "
            f"site also {', '.join(SITE_FAMILIES)})"
        )
    if not math.isfinite(args.total_load_mbps) or not args.total_load_mbps > 0:
        raise InputError(f"--total-load-mbps: must be positive, got {args.total_load_mbps}")
    environment = check_environment(args.environment, "--environment", on_disk=True)
    area = AreaConfig(environment=environment)
    check_family_area(args.family, area, "--family")  # a site family: only on a site
    try:
        area_site(area)  # a site: sound and covering the area
    except InputError as exc:
        raise InputError(f"--environment: {str(exc).removeprefix('environment: ')}") from None
    total_load_bps = args.total_load_mbps * 1e6
    scenarios = generate_scenarios(
        args.n,
        args.users,
        seed=args.seed,
        area=area,
        total_load_bps=total_load_bps,
        family=args.family,
    )
    generator = {
        "family": args.family,
        "users": args.users,
        "seed": args.seed,
        "total_load_bps": total_load_bps,
    }
    save_scenarios(args.out, area, scenarios, extra={"generator": generator})
    print(
        f"wrote {len(scenarios)} scenarios with {args.users} users each "
        f"(family {args.family}) to {args.out}"
    )
    print(format_heterogeneity_histogram(scenarios, area))
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from sim.errors import InputError
    from sim.evaluate import evaluate_cases_file

    if not args.warmup_s >= 0:
        raise InputError(f"--warmup-s: must be >= 0, got {args.warmup_s}")
    if not args.measure_s > 0:
        raise InputError(f"--measure-s: must be > 0, got {args.measure_s}")
    if args.backend == "ns3":
        if args.expected:
            raise InputError("--expected: not available with --backend ns3 (ns-3 draws its fading)")
        from sim.ns3_backend import evaluate_cases_file_ns3  # InputError if ns-3 is missing

        summary, n_failed = evaluate_cases_file_ns3(
            args.cases,
            args.out,
            seed=args.seed,
            queueing=args.queueing,
            warmup_s=args.warmup_s,
            measure_s=args.measure_s,
        )
        print(summary)
        return 1 if n_failed else 0
    summary = evaluate_cases_file(
        args.cases,
        args.out,
        seed=None if args.expected else args.seed,
        queueing=args.queueing,
        warmup_s=args.warmup_s,
        measure_s=args.measure_s,
    )
    print(summary)
    return 0
