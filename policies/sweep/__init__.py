"""``tupa sweep``: a grid of ordinary training runs, on this machine or a Ray cluster.

A sweep file (YAML, :mod:`.spec`) names the grid: algorithms, strategies, episode budgets,
seeds, worlds, channel environments, hyper-parameters and the test sets each run is evaluated
on. Every point of the grid is a *trial*: one ``tupa train`` run (the same
:func:`policies.training.training.train`, the same ``model.zip`` + ``model.json``, learning curve
and TensorBoard logs) in its own directory ``OUT/trials/<trial id>/``, so a sweep's run and a
hand-run training are interchangeable.

* :mod:`.spec`: reading and checking the sweep file, expanding the grid into trials with
  stable ids (a hash of everything that shapes the run).
* :mod:`.state`: ``OUT/sweep.json``, each trial's status, attempts and result, written
  atomically after every change: rerunning the command resumes, skipping finished trials.
* :mod:`.trial`: what a worker runs for one trial (one CPU thread, a fresh process).
* :mod:`.runner`: the scheduler shared by both backends: submits trials, retries failures a
  bounded number of times, records them, draws the progress table and writes the summary.
* :mod:`.local_backend`: one spawned process per trial, as many at once as the machine has
  cores. :mod:`.ray_backend`: one Ray task per trial (imported only with ``--backend ray``).
* :mod:`.fanout`: ``tupa eval --backend``, a large test set in slices on the same backends.
* :mod:`.cli`: ``tupa sweep`` (argparse only).

``tupa report --results OUT`` merges a finished sweep (:mod:`policies.report.sweep`).

Nothing heavy is imported here: ``tupa --help`` loads this package.
"""
