"""`yauyau plot FIT.json --out FIG.png`: the profile log-likelihood that `yauyau fit --profile NAME --json`
wrote (issue 39): ℓ_p(NAME) − ℓ̂ on its grid, the estimate, the 95% profile interval's level
ℓ̂ − χ²₁(0.95)/2 = ℓ̂ − 1.92, and the estimate ± 1.96 standard errors (the observed information's
quadratic, dashed) for comparison.  PNG or SVG by the suffix of --out (matplotlib, Agg)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

HALF_CHI2_95 = 0.5 * 3.841458820694124  # χ²₁'s 0.95 quantile over 2


def read_fit(path: str) -> dict:
    """FIT.json's profile, checked: {"name", "grid", "loglik"} with the estimate and stderr of name;
    InputError naming ``estimates`` (unreadable) or ``profile`` (absent or malformed)."""
    from yauyau.solver.errors import InputError

    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError("estimates", f"cannot read {path} as JSON: {exc}") from None
    profile = data.get("profile") if isinstance(data, dict) else None
    if not isinstance(profile, dict):
        raise InputError("profile", f"{path} has no profile: write it with yauyau fit ... --profile NAME "
                                    "--json > FIT.json")
    if "error" in profile:
        raise InputError("profile", f"{path}: the profile could not be computed: {profile['error']}")
    grid, loglik = profile.get("grid"), profile.get("loglik")
    ok = (isinstance(grid, list) and isinstance(loglik, list) and len(grid) == len(loglik) >= 2
          and all(isinstance(v, (int, float)) for v in grid)
          and all(v is None or isinstance(v, (int, float)) for v in loglik))  # null: not finite there
    if not ok:
        raise InputError("profile", f"{path}: profile needs grid and loglik, lists of numbers of one length")
    name = profile.get("name")
    estimates, stderr = data.get("estimates") or {}, data.get("stderr") or {}
    return {"name": name, "grid": grid, "loglik": loglik, "estimate": estimates.get(name),
            "stderr": stderr.get(name), "best": data.get("loglik")}


def draw(fit: dict, title: str):
    import numpy as np
    from matplotlib.figure import Figure

    grid = np.array(fit["grid"], dtype=float)
    loglik = np.array([math.nan if v is None else v for v in fit["loglik"]], dtype=float)
    best = fit["best"] if isinstance(fit["best"], (int, float)) and math.isfinite(fit["best"]) else math.nan
    best = float(np.nanmax(np.append(loglik, best)))
    fig = Figure(figsize=(6.4, 4.0), layout="constrained")
    ax = fig.subplots()
    ax.plot(grid, loglik - best, marker="o", markersize=3, color="tab:blue", label="profile log-likelihood")
    ax.axhline(-HALF_CHI2_95, color="gray", linestyle=":", label="95% profile level (−1.92)")
    estimate, se = fit["estimate"], fit["stderr"]
    if isinstance(estimate, (int, float)) and math.isfinite(estimate):
        ax.axvline(estimate, color="black", linewidth=0.9, label=f"estimate {estimate:.4g}")
        if isinstance(se, (int, float)) and math.isfinite(se) and se > 0:
            ax.plot(grid, -0.5 * ((grid - estimate) / se) ** 2, color="tab:red", linestyle="--",
                    label=f"quadratic of the standard error {se:.3g}")
    low = np.nanmin(loglik - best)
    ax.set_ylim(max(low, -8.0 * HALF_CHI2_95) - 0.5, 0.5)
    ax.set_xlabel(str(fit["name"]))
    ax.set_ylabel("log-likelihood − maximum")
    ax.legend(loc="best", fontsize="small")
    fig.suptitle(title, fontsize="medium")
    return fig


def run(args: argparse.Namespace, out: Path) -> int:
    from yauyau.solver.errors import InputError

    for option in ("smoothed", "truth", "density"):
        if getattr(args, option):
            raise InputError(option, "does not apply to a FIT.json (its profile is drawn alone)")
    fit = read_fit(args.estimates)
    return save(draw(fit, args.title or f"{Path(args.estimates).name}: profile of {fit['name']}"), out)


def save(fig, out: Path) -> int:
    """Write a figure of either plot (InputError naming ``out`` when it cannot be), print its path: exit
    status 0."""
    from yauyau.solver.errors import InputError

    try:
        fig.savefig(out, dpi=110)
    except OSError as exc:
        raise InputError("out", f"cannot write {out}: {exc}") from None
    print(out)
    return 0
