"""Test PSNR against the budget and against the steps, primitives 128 px, compact, from `nerfgauge bench train`
folders (docs/results.md: q1 with --budgets 600,1200, q2 with --budgets 2400):
`python docs/benchmarks/psnr_against_budget_to_2400.py q1 q2 OUT.png`."""
import json
import sys
import matplotlib; matplotlib.use("Agg")
import matplotlib.pyplot as plt
rows = [r for f in sys.argv[1:-1] for r in json.load(open(f"{f}/train.json"))["rows"]]
rows.sort(key=lambda r: r["budget"])
for r in rows:
    print(f"{r['budget']:.0f} s: {r['steps']} steps, {r['steps_per_second']:.1f} steps/s, test {r['psnr']:.2f} "
          f"(edges {r['psnr_edges']:.2f}, interior {r['psnr_interior']:.2f}), SSIM {r['ssim']:.4f}")
fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
for ax, key, label in ((axes[0], "budget", "training budget (s)"), (axes[1], "steps", "steps")):
    xs = [r[key] for r in rows]
    for part, style in (("psnr", "o-"), ("psnr_interior", "s--"), ("psnr_edges", "^:")):
        ax.plot(xs, [r[part] for r in rows], style, label=part.replace("psnr_", "") if part != "psnr" else "whole frame")
    ax.set_xscale("log"); ax.set_xlabel(label); ax.set_ylabel("test PSNR (dB)"); ax.grid(alpha=0.3)
axes[0].legend(fontsize=8)
fig.suptitle("compact NeRF, primitives 128 px, 100 views (600 and 1200 s: one run; 2400 s: another run, 13.6 against 10.3 steps/s)", fontsize=8)
fig.tight_layout(); fig.savefig(sys.argv[-1], dpi=110)
