"""The paper's error-propagation coefficients (table "Pseudo stars simulation results"), measured.

Monte Carlo (pooled over each source's default amplitudes, two decades) and the
analytic linear propagation, per axis and 2-D, against the paper's values; see
docs/centroids.md, "Error propagation coefficients".

    python benchmarks/error_propagation.py [--trials 400] [--seed 0] [--weighting pipeline|uniform]
                                           [--csv error_propagation_benchmark.csv] [--figure fig.png]
"""

import argparse
import sys
import time

from dice_core import error_budget

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--trials", type=int, default=400, help="trials per amplitude")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--weighting", choices=error_budget.WEIGHTINGS, default="pipeline")
parser.add_argument("--csv", help="also write the table's CSV here (one weighting: not the layout of the workflow's "
                                   "tables/error_propagation.csv, which has both, so never that path)")
parser.add_argument("--figure", help="also save the figure here (PNG or PDF)")
args = parser.parse_args()

start = time.perf_counter()
sweeps = [error_budget.sweep(s, trials=args.trials, seed=args.seed, weighting=args.weighting)
          for s in error_budget.SOURCES]
rows = error_budget.error_propagation_table(sweeps)
elapsed = time.perf_counter() - start

print("| source | per axis (MC) | 2-D (MC) | analytic per axis | analytic 2-D | Cramer-Rao per axis "
      "| paper | convention matching the paper | amplitude for 5e-6 pixel | paper's |")
print("|---|---:|---:|---:|---:|---:|---:|---|---:|---:|")
for r in rows:
    bound = "" if r["cramer_rao"] is None else f"{r['cramer_rao']:.3f}"
    paper_req = "" if r["paper_requirement"] is None else f"{r['paper_requirement']:.1e}"
    print(f"| {r['source']} | {r['coefficient']:.3f} +- {r['error']:.3f} | {r['coefficient_2d']:.3f} +- "
          f"{r['error_2d']:.3f} | {r['analytic']:.3f} | {r['analytic_2d']:.3f} | {bound} | "
          f"{r['paper_coefficient']:.2f} | {r['convention_matching_paper']} | {r['requirement_for_5e-6']:.2e} | "
          f"{paper_req} |")
print(f"\n{args.weighting} weights, {args.trials} trials x {len(sweeps[0].runs)} amplitudes per source, "
      f"seed {args.seed}: {elapsed:.1f} s", file=sys.stderr)
if args.csv:
    if args.csv.replace("\\", "/").endswith("tables/error_propagation.csv"):
        sys.exit(f"--csv {args.csv}: that is the workflow's product (both weightings in one row per source); "
                 "write this one-weighting table elsewhere")
    error_budget.write_error_propagation_csv(rows, args.csv)
if args.figure:
    from dice_core import plotting

    fig = plotting.error_propagation_figure(sweeps)
    fig.savefig(args.figure, dpi=120)
    plotting.plt.close(fig)
