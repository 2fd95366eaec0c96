"""The paper's figures and tables from ``tupa eval`` results: ``tupa report``.

:func:`build_report` reads every eval file in a results directory and the learning curve beside
them (:mod:`.inputs`, :mod:`.curves`), computes the numbers (:mod:`.stats`), renders the figures
(:mod:`.figures`) and ``results.md`` (:mod:`.markdown`), and only then writes them, each file
atomically: ``utility_cdf.png``, ``throughput_cdf.png``, ``delay_cdf.png``, ``plr_cdf.png``,
``metrics_cdf.png`` (the three metric CDFs side by side, as the paper's figure),
``utility_by_heterogeneity.png``, ``learning_curve.png`` (only with a learning curve),
``altitude.png`` (only when an eval file has altitude profiles: :mod:`.altitude`) and
``results.md`` (the tables behind the figures and the paper's two headline numbers as we
measure them). Summaries are recomputed from the per-scenario rows, not copied from the files.

The trainer writes the learning curve with :func:`policies.report.curves.write_learning_curve`;
importing this package does not load matplotlib. Given a ``tupa sweep`` directory, the report
merges the sweep instead (:mod:`.sweep`); given fleet evaluations (``tupa eval --uavs K``), the
fleet figures and tables (:mod:`.fleet`).
"""

from __future__ import annotations

from pathlib import Path

from policies.report.altitude import FIGURE_FILE as ALTITUDE_FIGURE
from policies.report.altitude import altitude_figure, altitude_lines, load_altitude_profiles
from policies.report.figures import line_styles, render_figures
from policies.report.inputs import Warn, load_inputs, stderr_warning
from policies.report.markdown import render_markdown
from policies.report.output import REPORT_FILE, ReportFiles, write_report_files
from policies.report.stats import headlines, heterogeneity_bins
from sim.errors import InputError

__all__ = ["REPORT_FILE", "ReportFiles", "build_report"]


def build_report(results_dir: Path, out_dir: Path, warn: Warn = stderr_warning) -> ReportFiles:
    """Read the eval files (and ``learning_curve.json`` if present) in ``results_dir`` and
    write the figures and ``results.md`` to ``out_dir`` (created if missing).

    Everything is read, checked and rendered before the first file is written, so bad input
    (:class:`InputError`) leaves ``out_dir`` untouched. Warnings (skipped files, differing
    evaluation settings) go to ``warn``.
    """
    results_dir, out_dir = Path(results_dir), Path(out_dir)
    from policies.sweep.state import is_sweep_dir

    if is_sweep_dir(results_dir):  # a tupa sweep directory: policies/report/sweep.py
        from policies.report.sweep import build_sweep_report

        return build_sweep_report(results_dir, out_dir, warn)
    from policies.report.fleet import build_fleet_report, holds_fleet_results

    if holds_fleet_results(results_dir):  # tupa eval --uavs K files: policies/report/fleet.py
        return build_fleet_report(results_dir, out_dir, warn)
    results, learning = load_inputs(results_dir, warn)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out: {out_dir}: exists and is not a directory")
    figures = render_figures(results, learning)
    profiles = load_altitude_profiles(results_dir)
    if profiles:
        styles = line_styles([r.policy for r in results])
        figures[ALTITUDE_FIGURE] = altitude_figure(profiles, results, styles, warn)
    markdown = render_markdown(results, learning, results_dir, altitude_lines(profiles))
    written = write_report_files(out_dir, {**figures, REPORT_FILE: markdown})
    lines = headlines(results, heterogeneity_bins(results))
    return ReportFiles(written=tuple(written), headlines=tuple(lines))
