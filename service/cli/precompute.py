"""`yauyau precompute SPEC --store DIR`: the offline stage, stored as one HDF5 file.

Solves the Fokker–Planck / Kolmogorov propagators of the spec's model over dt for every basis
function (solver.offline.precompute, seed 002 §5) and saves them in the model store under the
content hash of the spec.  The filter method is chosen here, once: ``auto`` asks the
estimation-algebra analysis (in a process of its own, killed 2 s after --time-limit: a wall-clock
bound) and the choice and its reason are stored in the file, so `yauyau filter` and `yauyau serve`
never analyse again.  The model id is the LAST line of
stdout (the only one); messages and the progress bar go to stderr.  The bar is shown only when
stderr is a terminal and --quiet is not given.  An id already in the store is not recomputed (its
file is verified) unless --force.  A mesh coarser than the measured default of the spec's dimension
(solver/defaults.py) is warned about before the solve, naming the field and the fix.
"""

from __future__ import annotations

import argparse
import os
import sys

DEFAULT_STORE = "var/store"


def default_store() -> str:
    """The model store of a command given no --store: $YAUYAU_STORE, else var/store."""
    return os.environ.get("YAUYAU_STORE", DEFAULT_STORE)


def store_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--store", default=default_store(),
                        help="model store directory (default: $YAUYAU_STORE or %(default)s)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", help="model spec file (.toml or .json)")
    store_argument(parser)
    parser.add_argument("--workers", type=int, default=None,
                        help="local Dask worker processes solving the propagators (default: min(4, CPU "
                             "count); 1: in this process, no cluster)")
    parser.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                        help="run the solves as tasks on this running Dask cluster (its workers need "
                             "yauyau installed; start them with --nthreads 1); --workers is then unused")
    parser.add_argument("--quiet", action="store_true", help="no progress bar and no messages on stderr")
    parser.add_argument("--force", action="store_true", help="recompute even if the model is stored")
    parser.add_argument("--time-limit", type=float, default=60.0, metavar="T",
                        help="seconds the estimation-algebra analysis may take to choose the method when the "
                             "spec says method = auto (default %(default)g; past it: the general engine). A "
                             "wall-clock limit: the analysis runs in a process of its own, killed 2 s later")
    parser.add_argument("--compress", action="store_true",
                        help="gzip the float arrays too (about 1/3 smaller in 2-D, loads much slower)")


def _say(args: argparse.Namespace, message: str) -> None:
    if not args.quiet:
        print(f"yauyau precompute: {message}", file=sys.stderr)


def _progress_bar(args: argparse.Namespace, total: int):
    from tqdm import tqdm

    # disable=None: tqdm turns itself off when stderr is not a terminal
    return tqdm(total=total, desc="propagators", unit="fn", file=sys.stderr,
                disable=True if args.quiet else None, leave=False)


def _already_stored(args: argparse.Namespace, store, mid: str) -> bool:
    from yauyau.storage.errors import StoreError

    if args.force or not store.exists(mid):
        return False
    try:
        store.load(mid)  # verifies format, hash and checksums
    except StoreError as exc:
        _say(args, f"stored file of {mid} is unusable ({exc.message}); recomputing")
        return False
    _say(args, f"model {mid} is already in {store.directory} (use --force to recompute)")
    return True


def run(args: argparse.Namespace) -> int:
    from yauyau.solver import load_spec
    from yauyau.solver.errors import InputError
    from yauyau.solver.offline.pipeline import default_workers
    from yauyau.storage.model_store import ModelStore, model_id

    from yauyau.api import save_solved

    spec = load_spec(args.spec)
    workers = default_workers() if args.workers is None else args.workers
    if workers < 1:
        raise InputError("workers", "must be a positive integer")
    if args.scheduler is not None and not args.scheduler.startswith(("tcp://", "tls://", "inproc://")):
        raise InputError("--scheduler", f"must be a Dask scheduler address such as tcp://HOST:8786, got "
                                        f"{args.scheduler!r}")
    if not 0.1 <= args.time_limit <= 3600:  # also refuses nan and inf
        raise InputError("--time-limit", "must be between 0.1 and 3600 seconds")
    spec_json = spec.canonical_json()
    store, mid = ModelStore(args.store, compress_floats=args.compress), model_id(spec_json)
    store.ensure_writable()  # fail before the (long) computation, not after
    if _already_stored(args, store, mid):
        _warm_kernels(args)
        print(mid)
        return 0

    _warn_if_coarse(args, spec)
    total = spec.discretization.basis
    with _progress_bar(args, total) as bar:
        def progress(done: int, of: int) -> None:
            bar.total = of
            bar.update(done - bar.n)
        saved, solved = save_solved(store, spec, workers=workers, time_limit=args.time_limit,
                                    progress=progress, scheduler=args.scheduler)
    _say(args, f"method {solved.method}: {solved.method_reason}")
    if spec.domain.follow and solved.method != "yau-yau":
        _say(args, f"note: domain.follow has no effect here: {solved.method} is exact for this model and "
                   "needs no ball; set method = \"yau-yau\" to filter on a ball that follows the state")
    size = store.path(saved).stat().st_size
    what = f"{total} basis functions" if solved.offline is not None else "mesh-free, no offline arrays"
    atlas = getattr(solved.offline, "atlas", None)
    if atlas is not None:
        what += f", an atlas of {atlas.size} centres over the region"
    _say(args, f"stored '{spec.name}' ({what}, {solved.seconds:.1f} s, "
               f"{size / 1e6:.2f} MB) as {store.path(saved)}")
    _warn_if_unresolved(args, spec, solved)
    _warm_kernels(args)
    _row_costs(args, spec, solved)
    print(saved)
    return 0


def _warm_kernels(args: argparse.Namespace) -> None:
    """Compile the engine's row loops into numba's on-disk cache (or load them from it), so that
    ``yauyau filter`` and the service do not compile them on their first chunk; say what it cost."""
    from yauyau.solver.jit import cache_dir
    from yauyau.solver.warm import warm_kernels

    seconds = warm_kernels()
    if seconds is not None:
        _say(args, f"row loops compiled or loaded from numba's cache in {seconds:.1f} s ({cache_dir()}; "
                   "YAUYAU_CACHE_DIR)")


def _row_costs(args: argparse.Namespace, spec, solved) -> None:
    """One line: the µs per regular and per irregular row of the stored model, measured on a few hundred
    rows (solver/engine/rowcost.py; the general engine only)."""
    if solved.offline is None or solved.method != "yau-yau" or args.quiet:
        return
    from yauyau.solver.engine.filter import build
    from yauyau.solver.engine.rowcost import row_costs
    from yauyau.solver.model import compile_model

    _say(args, row_costs(build(compile_model(spec), solved.offline)).line())


def _warn_if_coarse(args: argparse.Namespace, spec) -> None:
    """Before the solve: one line when the mesh is coarser than the measured default of the spec's
    dimension (solver/check.py ``coarser_than_measured``, a rule: nothing is filtered)."""
    from yauyau.solver.check import coarser_than_measured  # lazy, as every import here: a fast CLI start

    coarse = coarser_than_measured(spec)
    if coarse is not None:
        _say(args, f"warning: {coarse[0]}: {coarse[1]}")


def _warn_if_unresolved(args: argparse.Namespace, spec, solved) -> None:
    """Where the truth is free (a linear model: the exact Kalman filter), filter a few simulated paths
    with the arrays just solved and warn when they do not resolve the posterior (yauyau check does the
    full check, for any model)."""
    from yauyau.solver.check import resolution_check

    if solved.offline is None or solved.method != "yau-yau" or args.quiet:
        return
    from yauyau.solver.errors import YauyauError

    try:  # the file is stored already: a check that cannot run is a warning, never a failed precompute
        report = resolution_check(spec, suggest=False, offline=solved.offline, exact_only=True)
    except YauyauError as exc:
        _say(args, f"warning: the resolution check could not run ({exc}); run `yauyau check {args.spec}`")
        return
    if report is not None and not report.requested.ok:
        r = report.requested
        _say(args, f"warning: basis {r.basis} does not resolve this model's posterior: on simulated paths "
                   f"the mean is {r.mean_gap:.3g} from the exact filter on average ({r.degenerate:.0%} "
                   f"degenerate steps); run `yauyau check {args.spec}` for a basis that does")
