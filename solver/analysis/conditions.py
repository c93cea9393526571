"""The structural conditions of a model: Wong matrix, η, (C1)/(C'1), (C2), (C3), the linear case and
the structure of the non-maximal-rank class of seed 004.

For dx = f dt + G dv, dy = h dt + dw (a = GQGᵀ, E dw dwᵀ = R dt):

* the Wong matrix ω_ij = ∂f_j/∂x_i − ∂f_i/∂x_j (seed 004 Def. 4, seed 002 (2.5)); (C'1) asks it to
  be constant, equivalently (C1) f = ℓ + ∇F with ℓ affine (seed 000 Theorem 2.1, (2.6));
* η = fᵀa⁻¹f + div f + hᵀR⁻¹h (seed 000 (2.5), seed 004 §II; = |f|² + div f + |h|² when a = R = I),
  so that L0 = ½(Dᵀ a D − η) with D = ∇ − a⁻¹f; (C3) asks η to be a quadratic polynomial (seed 000
  (2.8)) and (C2) h to be affine (seed 000 (2.7));
* seed 004 §III: (I) ω_kj = 0, (II) η = A x_k² + B x_k + γ(x'), (v) h affine in x_k alone, and the
  items (i)–(v) of its class, with x_k in the role of x1.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import sympy as sp

from ..errors import SpecError
from ..model import Model
from .budget import BoundReached, current_budget, expand
from .operators import exact_matrix, is_identity, is_zero, observation_energy, tidy
from .yau_jia import yau_jia_structure


def wong_matrix(model: Model) -> sp.Matrix:
    """ω_ij = ∂f_j/∂x_i − ∂f_i/∂x_j   (seed 004 Def. 4, seed 002 (2.5))."""
    x, f, n = model.symbols, model.drift, model.n
    return sp.Matrix(n, n, lambda i, j: _entry(sp.diff(f[j], x[i]) - sp.diff(f[i], x[j]), x))


def whitened_wong_matrix(model: Model) -> sp.Matrix:
    """a Jᵀ − J a (J = ∂f/∂x): L Ω̃ Lᵀ for the Wong matrix Ω̃ of z = L⁻¹x, a = LLᵀ; = Ω when a = I."""
    J = sp.Matrix(model.drift).jacobian(model.symbols)
    a = exact_matrix(model.a)
    return (a * J.T - J * a).applyfunc(lambda w: _entry(w, model.symbols))


def _entry(expr: sp.Expr, symbols) -> sp.Expr:
    """Expanded, and exactly 0 when it vanishes identically (a zero test, not sp.simplify)."""
    e = expand(expr)
    return sp.Integer(0) if e != 0 and is_zero(e, symbols) else e


SINGULAR_A = ("not defined: the diffusion a is singular (a coordinate without noise), and eta = "
              "f^T a^-1 f + ... needs a^-1; the Yau filtering-system theory (C3, Theorem 3.1) assumes a "
              "nondegenerate diffusion")


def is_singular(a) -> bool:
    """The diffusion a (positive semi-definite, as the spec checks) has a zero eigenvalue: noise-free
    coordinates (constant-velocity tracking: a = diag(0, q))."""
    return exact_matrix(a).det() == 0


def eta(model: Model) -> sp.Expr:
    """η = fᵀa⁻¹f + div f + hᵀR⁻¹h   (seed 004 §II with a = R = I: |f|² + div f + |h|²)."""
    f = sp.Matrix(model.drift)
    div_f = sum(sp.diff(fi, xi) for fi, xi in zip(model.drift, model.symbols, strict=True))
    a_inv = exact_matrix(model.a).inv()
    e = expand((f.T * a_inv * f)[0, 0] + div_f + observation_energy(model))
    current_budget().check_size(e)
    return tidy(e)


def is_constant(expr: sp.Expr, symbols) -> bool:
    return all(is_zero(sp.diff(expr, s), symbols) for s in symbols)


def polynomial_degree_at_most(expr: sp.Expr, symbols, degree: int) -> bool:
    """All derivatives of order degree+1 vanish (works for non-polynomial expressions too)."""
    for combo in itertools.combinations_with_replacement(symbols, degree + 1):
        if not is_zero(sp.diff(expr, *combo), symbols):
            return False
    return True


@dataclass(frozen=True)
class Condition:
    holds: bool | None  # None: not decided within the bounds of the analysis
    detail: str
    title: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"holds": self.holds, "title": self.title, "detail": self.detail}


def seed004_structure(model: Model, k: int) -> dict[str, Any] | None:
    """The structure Theorem 1 of seed 004 needs, with x_k playing x1; None if it fails.

    Conditions (I) ω_kj = 0 for all j and (II) η = A x_k² + B x_k + γ(other x) with constants
    A, B, and h affine in x_k alone (v).  Returns A, B, the slopes c = ∂h/∂x_k, offsets h(x_k=0).
    """
    x, n = model.symbols, model.n
    xk = x[k]
    others = [s for i, s in enumerate(x) if i != k]
    omega = wong_matrix(model)
    if any(omega[k, j] != 0 for j in range(n)):
        return None
    e = expand(eta(model))
    A = constant_value(sp.diff(e, xk, 2) / 2, x)
    B = constant_value(sp.diff(e, xk).subs(xk, 0), x)
    if A is None or B is None or not polynomial_degree_at_most(e, [xk], 2):
        return None
    slopes, offsets = [], []
    for hi in model.observation:
        c1 = constant_value(sp.diff(hi, xk), x)
        if c1 is None or not all(is_zero(sp.diff(hi, s), x) for s in others):
            return None
        slopes.append(c1)
        offsets.append(tidy(hi.subs(xk, 0)))
    return {"coordinate": k, "A": A, "B": B, "slopes": slopes, "offsets": offsets,
            "gamma": tidy(e - A * xk**2 - B * xk)}


def constant_value(expr: sp.Expr, symbols) -> sp.Expr | None:
    """The number expr equals if it is constant in the symbols (exactly: sin² + cos² -> 1), else None."""
    e = tidy(expr)
    if not (e.free_symbols & set(symbols)):
        return e
    if not is_constant(e, symbols):
        return None
    value = tidy(e.subs({s: 0 for s in symbols}))  # constant: its value anywhere, e.g. at the origin
    return value if value.is_finite and not value.free_symbols else None


def _seed004_items(model: Model, k: int) -> dict[str, Condition]:
    """Conditions (i)–(v) of seed 004 §III with x_k in the role of x1."""
    x, f, n = model.symbols, model.drift, model.n
    xk = x[k]
    others = [s for i, s in enumerate(x) if i != k]
    affine = all(is_zero(sp.diff(fi, xk, 2), x) for fi in f)
    a_coef = [tidy(sp.diff(fi, xk)) for fi in f]
    phi = [tidy(fi - ai * xk) for fi, ai in zip(f, a_coef, strict=True)]
    items = {"(i) f_i = a_i(x') x_k + phi_i(x')": Condition(affine, "f affine in x_k")}
    ii = affine and all(is_zero(sp.diff(phi[k], x[j]) - a_coef[j], x) for j in range(n) if j != k)
    items["(ii) d phi_k/dx_j = a_j"] = Condition(ii, "")
    norm2 = constant_value(sum(ai**2 for ai in a_coef), x)
    iii = (affine and constant_value(a_coef[k], x) is not None and norm2 is not None
           and bool(norm2 > 0))
    shown = norm2 if norm2 is not None else tidy(sum(ai**2 for ai in a_coef))
    items["(iii) a_k constant, sum a_i^2 positive constant"] = Condition(bool(iii), f"sum a_i^2 = {shown}")
    iv_expr = tidy(2 * sum(ai * pi for ai, pi in zip(a_coef, phi, strict=True))
                   + sum(sp.diff(a_coef[j], x[j]) for j in range(n) if j != k))
    items["(iv) 2 sum a_i phi_i + sum_j d a_j/dx_j constant"] = Condition(
        affine and is_constant(iv_expr, x), f"= {iv_expr}")
    v = all(polynomial_degree_at_most(hi, [xk], 1) and all(is_zero(sp.diff(hi, s), x) for s in others)
            for hi in model.observation)
    items["(v) h affine in x_k only"] = Condition(v, "")
    return items


@dataclass
class Facts:
    """The structural conditions; None marks an item not decided within the bounds."""

    omega: Any = None
    omega_a: Any = None
    eta: Any = None
    eta_why: str = ""  # why η is not defined (a singular diffusion), shown instead of it
    c1: bool | None = None
    c2: bool | None = None
    c3: bool | None = None
    linear: bool | None = None
    wong_constant: bool | None = None
    k: int | None = None
    structure: Any = None
    structure_holds: bool | None = None
    seed004: dict = field(default_factory=dict)
    yau_jia: bool | None = None  # seed 001 (4.1) and (4.2) for the model's a
    yau_jia_detail: str = ""
    stopped_by: list = field(default_factory=list)
    numeric: int = 0

    def decide(self, fn):
        """fn() under the current budget, or None (recorded) when it reaches a bound."""
        try:
            return fn()
        except BoundReached as bound:
            if str(bound) not in self.stopped_by:
                self.stopped_by.append(str(bound))
            return None

    def decided(self) -> dict[str, Any]:
        """What was decided, JSON-safe (the expressions left out): what an analysis process sends its
        parent before it builds the estimation algebra, so that a process killed later still leaves
        these (solver/analysis/isolated.py)."""
        data = {name: getattr(self, name) for name in _DECIDED}
        data["seed004"] = {key: c.to_dict() for key, c in self.seed004.items()}
        return data

    @classmethod
    def from_decided(cls, data: dict[str, Any]) -> "Facts":
        """The facts :meth:`decided` sent (the Wong matrix, η and the seed 004 structure not computed)."""
        seed004 = {key: Condition(c["holds"], c["detail"], c["title"]) for key, c in data["seed004"].items()}
        return cls(**{name: data[name] for name in _DECIDED}, seed004=seed004)


_DECIDED = ("eta_why", "c1", "c2", "c3", "linear", "wong_constant", "k", "structure_holds", "yau_jia",
            "yau_jia_detail", "stopped_by", "numeric")


def all_of(values) -> bool | None:
    """Three-valued and: False if any is False, None if any is undecided, else True."""
    values = list(values)
    return False if False in values else (None if None in values else True)


def decide_conditions(model: Model) -> Facts:
    x = model.symbols
    a_is_identity = is_identity(model.a)
    facts = Facts(k=observed_coordinate(model))
    # the cheap conditions first (second derivatives of f and h): decided even when the Wong matrix
    # and η of a large model use up the time
    facts.c2 = all_of(facts.decide(lambda hi=hi: polynomial_degree_at_most(hi, x, 1))
                    for hi in model.observation)
    affine_f = all_of(facts.decide(lambda fi=fi: polynomial_degree_at_most(fi, x, 1)) for fi in model.drift)
    facts.linear = all_of([facts.c2, affine_f])
    facts.omega = facts.decide(lambda: wong_matrix(model))
    facts.omega_a = facts.omega if a_is_identity else facts.decide(lambda: whitened_wong_matrix(model))
    if is_singular(model.a):  # η needs a⁻¹; (C3) and Theorem 3.1 a nondegenerate diffusion
        facts.eta_why, facts.c3 = SINGULAR_A, False
    else:
        facts.eta = facts.decide(lambda: eta(model))
    if facts.omega_a is not None:
        facts.c1 = all_of(facts.decide(lambda w=w: is_constant(w, x)) for w in facts.omega_a)
    if facts.omega is not None:
        facts.wong_constant = all_of(facts.decide(lambda w=w: is_constant(w, x)) for w in facts.omega)
    if facts.eta is not None:
        facts.c3 = facts.decide(lambda: polynomial_degree_at_most(facts.eta, x, 2))
    if facts.k is not None and a_is_identity:
        facts.structure = facts.decide(lambda: seed004_structure(model, facts.k) or False)
        facts.structure_holds = None if facts.structure is None else facts.structure is not False
        if model.n > 1:
            facts.seed004 = facts.decide(lambda: _seed004_items(model, facts.k)) or {}
    else:
        facts.structure_holds = False
    facts.yau_jia, facts.yau_jia_detail = _yau_jia_fact(model, facts)
    return facts


def _yau_jia_fact(model: Model, facts: Facts) -> tuple[bool | None, str]:
    try:
        structure = facts.decide(lambda: yau_jia_structure(model))
    except SpecError as exc:
        return False, exc.message
    if structure is None:
        return None, ""
    return True, structure.describe(model)


def observed_coordinate(model: Model) -> int | None:
    """The single state coordinate h depends on (x1 of seed 004 §III), if there is one."""
    used = {i for hi in model.observation for i, s in enumerate(model.symbols) if hi.has(s)}
    return next(iter(used)) if len(used) == 1 else None
