"""``tupa site build``: a district prepared for the fast model (:mod:`sim.sites.build`).

Registered by :func:`sim.cli.register`; the ray tracer is imported only inside the handler.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from sim.sites.build import BuildSpec


def register(subparsers: argparse._SubParsersAction) -> None:
    site = subparsers.add_parser(
        "site", help="ray-traced districts as channel environments", allow_abbrev=False
    )
    site_sub = site.add_subparsers(dest="site_command", required=True)
    build = site_sub.add_parser(
        "build",
        allow_abbrev=False,
        help="ray-trace a district with Sionna RT into a site directory "
        "(needs pip install 'tupa[sites]' and libllvm19)",
    )
    source = build.add_mutually_exclusive_group(required=True)
    source.add_argument("--scene", help="a scene shipped with sionna-rt (munich, ...)")
    source.add_argument("--scene-file", help="a Mitsuba XML scene of your own")
    build.add_argument(
        "--center",
        help="X,Y of the area's centre in the scene's frame, metres (default: the scene's centre)",
    )
    build.add_argument("--size-m", type=float, default=500.0, help="the square area's side")
    build.add_argument("--cell-m", type=float, default=5.0, help="ground cell side (≤ 5 m)")
    build.add_argument(
        "--grid-xy-m", type=float, default=25.0, help="UAV grid spacing in x and y (default 25)"
    )
    build.add_argument(
        "--grid-z-m",
        default="25,37.5,50,62.5,75,87.5,100",
        help="UAV grid altitudes, comma-separated metres (default every 12.5 m from 25 to 100)",
    )
    build.add_argument(
        "--samples", type=int, default=2_000_000, help="rays per UAV grid point (default 2e6)"
    )
    build.add_argument("--max-depth", type=int, default=3, help="bounces per ray")
    build.add_argument("--batch", type=int, default=8, help="UAV grid points per ray-tracer call")
    build.add_argument("--out", type=Path, required=True, help="the site directory")
    build.set_defaults(handler=_build)


def _numbers(option: str, text: str, count: int | None = None) -> tuple[float, ...]:
    from sim.errors import InputError

    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise InputError(f"{option}: must be comma-separated numbers, got {text!r}") from None
    if (count is not None and len(values) != count) or not all(map(math.isfinite, values)):
        what = f"{count} finite numbers" if count else "finite numbers"
        raise InputError(f"{option}: must be {what}, got {text!r}")
    return values


def _build(args: argparse.Namespace) -> int:
    from sim.errors import InputError
    from sim.sites.build import build_site

    if args.samples < 1:
        raise InputError(f"--samples: must be at least 1, got {args.samples}")
    if args.max_depth < 0:
        raise InputError(f"--max-depth: must be at least 0, got {args.max_depth}")
    center = _numbers("--center", args.center, 2) if args.center is not None else None
    spec = BuildSpec(
        scene=args.scene,
        scene_file=args.scene_file,
        center_xy_m=center,
        size_m=args.size_m,
        cell_m=args.cell_m,
        grid_xy_m=args.grid_xy_m,
        grid_z_m=_numbers("--grid-z-m", args.grid_z_m),
        batch=args.batch,
        solver={"samples_per_tx": args.samples, "max_depth": args.max_depth},
    )
    spec.check()
    site = build_site(spec, args.out)
    covered = float((site.loss_code != 65535).mean())
    print(
        f"site {args.out}: {site.cells_x}×{site.cells_y} cells of {site.cell_m:g} m, "
        f"{site.uav_x_m.size}×{site.uav_y_m.size}×{site.uav_z_m.size} UAV grid points, "
        f"{covered:.0%} of links with a path, built in {site.meta['build']['seconds']:g} s"
    )
    return 0
