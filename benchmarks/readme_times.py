"""The README's time claims, measured: each claim's command run as a user runs it, timed.

Each claim (:data:`CLAIMS`) is one ``tupa`` command of the README, run once as a fresh process
(into a fresh output directory, so that nothing is resumed or reused) and timed from start to
exit. The result is stated as the README states it (:func:`phrase`: ``about 3 min``, ``about
75 s``) together with the machine it was measured on (its cores, CPU model and load average
before and after: other work on the machine slows every command). ``tests/test_readme.py``
checks that the README line of each measured claim says that phrase and the core count, so a
claim cannot drift from its measurement.

Writes ``benchmarks/results/readme_times.json``; claims not run this time keep their earlier
measurement.

    python benchmarks/readme_times.py                        # every claim (about 3 min, 2 cores)
    python benchmarks/readme_times.py --only smoke-sweep     # one of them
    python benchmarks/readme_times.py --keep runs/readme-times   # keep what the commands wrote

A benchmark, not a test: it runs the commands for real, in real time.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "readme_times.json"
FORMAT = "tupa-readme-times/1"


@dataclass(frozen=True)
class Claim:
    """One time claim: the README line that makes it (found by ``anchor``, text on that line
    only) and the command it times; ``{out}`` in the command is a fresh directory."""

    anchor: str
    command: tuple[str, ...]


CLAIMS: dict[str, Claim] = {
    "smoke-sweep": Claim(
        anchor="tupa sweep sweeps/smoke.yaml --out runs/sweeps/smoke  ",
        command=("tupa", "sweep", "sweeps/smoke.yaml", "--out", "{out}/smoke"),
    ),
    "fleet-demo": Claim(
        anchor="tupa demo --uavs 3 ",
        command=("tupa", "demo", "--uavs", "3", "--out", "{out}/demo-fleet"),
    ),
}


def phrase(wall_s: float) -> str:
    """How the README states a measured time: to 5 s under 90 s, else to half a minute."""
    if wall_s < 90:
        return f"about {max(5, round(wall_s / 5) * 5)} s"
    minutes = round(wall_s / 30) / 2
    return f"about {minutes:g} min"


def machine() -> dict[str, Any]:
    """The cores this process may use, the CPU model, the platform."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cores": cores, "cpu": model, "platform": platform.platform()}


def run_claim(name: str, claim: Claim, out_dir: Path) -> dict[str, Any]:
    """Run ``claim``'s command once (``tupa`` from this Python's environment), timed."""
    tupa = Path(sys.executable).parent / "tupa"
    command = [str(tupa) if w == "tupa" else w.format(out=out_dir) for w in claim.command]
    shown = " ".join(w.format(out="OUT") for w in claim.command)
    print(f"{name}: {shown}", flush=True)
    load_before = os.getloadavg()
    cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    wall_s = time.perf_counter() - started
    cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if result.returncode != 0:
        raise SystemExit(f"{name}: exit {result.returncode}:\n{result.stderr[-3000:]}")
    cpu_s = (cpu_after.ru_utime - cpu_before.ru_utime) + (cpu_after.ru_stime - cpu_before.ru_stime)
    print(f"{name}: {wall_s:.1f} s ({phrase(wall_s)}), {cpu_s:.0f} s of CPU", flush=True)
    return {
        "command": shown,
        "wall_s": round(wall_s, 1),
        "cpu_s": round(cpu_s, 1),
        "phrase": phrase(wall_s),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "measured": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "anchor": claim.anchor,
        **machine(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--only", metavar="NAME,...", help=f"claims to measure (default: all of {list(CLAIMS)})"
    )
    parser.add_argument("--keep", type=Path, metavar="DIR", help="write the commands' output here")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    names = args.only.split(",") if args.only else list(CLAIMS)
    unknown = [n for n in names if n not in CLAIMS]
    if unknown:
        parser.error(f"--only: unknown claim(s) {unknown}; known: {list(CLAIMS)}")
    document = {"format": FORMAT, "claims": {}}
    if args.out.exists():
        document = json.loads(args.out.read_text())
    work = Path(tempfile.mkdtemp(prefix="tupa-readme-times-")) if args.keep is None else args.keep
    if args.keep is not None:
        for name in names:  # fresh output: nothing resumed
            for word in CLAIMS[name].command:
                if "{out}" in word:
                    shutil.rmtree(Path(word.format(out=work)), ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    try:
        for name in names:
            document["claims"][name] = run_claim(name, CLAIMS[name], work.resolve())
            document["claims"] = dict(sorted(document["claims"].items()))
            args.out.write_text(json.dumps(document, indent=2) + "\n")  # after each claim
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
