"""Scene formulas in x, y, z (domain coordinates): a small safe evaluator and the external potential.

A formula (``potential = "0.5*((x-0.5)/0.08)**2"``, an initial ``density``) is parsed with
:mod:`ast` and only a whitelist is accepted: numbers, ``x y z``, ``pi e``, ``+ - * / **``, unary
minus and the functions of :data:`FUNCS` (``step(u)``: 1 where u ≥ 0, else 0, for boxes); nothing is ever passed to ``eval``.
A condition (``left = "x < 0.5"``, ``[observables]``) parses with ``logic=True``, which adds
``< <= > >=`` (chained too), ``and``, ``or`` and ``not`` (1 where true, else 0; NumPy only). The parsed formula
is a tree of tuples, evaluated three ways: on NumPy arrays (:func:`numpy_value`), as Taichi
expressions at kernel-compile time (:func:`taichi_value`: a plain Python walk over the tree that
Taichi's compiler runs while it traces the calling ``ti.func``, so each formula compiles to straight
arithmetic), and differentiated symbolically (:func:`derivative`) for the particles' drift −½∇U.
"""
from __future__ import annotations

import ast
import functools
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .errors import ExprError

VARIABLES = ("x", "y", "z")  # axis 0, 1, 2
CONSTANTS = {"pi": math.pi, "e": math.e}
FUNCS = ("sin", "cos", "tan", "exp", "log", "sqrt", "abs", "tanh", "atan", "step")  # step(u): 1 where u >= 0, else 0
_BINARY = {ast.Add: "add", ast.Sub: "sub", ast.Mult: "mul", ast.Div: "div", ast.Pow: "pow"}
MAX_CHARS, MAX_DEPTH = 5_000, 100  # a formula's length and nesting (its tree is walked recursively)
_COMPARE = {ast.Lt: "lt", ast.LtE: "le", ast.Gt: "gt", ast.GtE: "ge"}  # conditions only (logic=True)
QUADRATURE = {1: 16, 2: 8, 3: 4}  # Gauss–Legendre points per axis for cell averages, by dimension


# ---------------------------------------------------------------------------------------
# the tree: ("num", v) | ("var", axis) | (op, left, right) | ("neg", a) | ("call", name, a)
# ---------------------------------------------------------------------------------------
def _num(v: float) -> tuple:
    return ("num", float(v))


def _is(t: tuple, v: float) -> bool:
    return t[0] == "num" and t[1] == v


def _make(op: str, a: tuple, b: tuple | None = None) -> tuple:
    """Node ``op`` of ``a`` (and ``b``), constants folded and 0/1 identities dropped, so that
    derivatives stay short."""
    if op == "neg":
        return _num(-a[1]) if a[0] == "num" else (a[1] if a[0] == "neg" else ("neg", a))
    if a[0] == "num" and b[0] == "num":
        with np.errstate(all="ignore"):  # NaN or inf where the formula has none: load.py refuses it
            return _num(numpy_value((op, a, b), ()))
    if op == "add":
        return b if _is(a, 0) else a if _is(b, 0) else ("add", a, b)
    if op == "sub":
        return _make("neg", b) if _is(a, 0) else a if _is(b, 0) else ("sub", a, b)
    if op == "mul":
        if _is(a, 0) or _is(b, 0):
            return _num(0)
        return b if _is(a, 1) else a if _is(b, 1) else ("mul", a, b)
    if op == "div":
        return _num(0) if _is(a, 0) else a if _is(b, 1) else ("div", a, b)
    return _num(1) if _is(b, 0) else a if _is(b, 1) else ("pow", a, b)


def parse(text: str, logic: bool = False) -> tuple:
    """The tree of formula ``text`` (``logic``: a condition, comparisons allowed); :class:`ExprError`
    naming what is not allowed."""
    if not isinstance(text, str) or not text.strip():
        raise ExprError(f"give a {'condition' if logic else 'formula'} in x, y, z as text")
    too_big = f"give a formula of at most {MAX_CHARS:,} characters and {MAX_DEPTH} levels of nesting"
    if len(text) > MAX_CHARS:
        raise ExprError(f"{quoted(text)} is too long: {too_big}")
    try:
        body = ast.parse(text.strip(), mode="eval").body
    except SyntaxError:
        raise ExprError(f"{quoted(text)} is not a formula: check its brackets and operators") from None
    except (RecursionError, MemoryError):  # the parser's own limit on nesting
        raise ExprError(f"{quoted(text)} is nested too deep: {too_big}") from None
    depth, level = 0, [(body, 1)]
    while level:  # its depth, without recursion (the term a + b + … + z is as deep as it is long)
        depth = max(depth, max(d for _, d in level))
        level = [(c, d + 1) for n, d in level for c in ast.iter_child_nodes(n) if not isinstance(c, ast.expr_context)]
    if depth > MAX_DEPTH:
        raise ExprError(f"{quoted(text)} is nested {depth} levels deep (a sum or product of n terms is n deep): "
                        f"{too_big}")
    return _node(body, logic)


def quoted(text: str) -> str:
    """A formula as a message quotes it: its start, if long."""
    return repr(text) if len(text) <= 60 else f"{text[:40]!r}… ({len(text):,} characters)"


def _node(n: ast.AST, logic: bool = False) -> tuple:
    allowed = f"use numbers, {', '.join(VARIABLES)}, pi, e, + - * / **{' < <= > >= and or not' * logic} and " \
              f"{', '.join(FUNCS)}"
    if logic and isinstance(n, ast.Compare) and all(type(o) in _COMPARE for o in n.ops):
        terms = [_node(c, logic) for c in (n.left, *n.comparators)]
        parts = [(_COMPARE[type(o)], a, b) for o, a, b in zip(n.ops, terms, terms[1:])]  # a < b < c: both
        return functools.reduce(lambda a, b: ("and", a, b), parts)
    if logic and isinstance(n, ast.BoolOp):
        return functools.reduce(lambda a, b: ("and" if isinstance(n.op, ast.And) else "or", a, b),
                                [_node(v, logic) for v in n.values])
    if logic and isinstance(n, ast.UnaryOp) and isinstance(n.op, ast.Not):
        return ("not", _node(n.operand, logic))
    if isinstance(n, ast.Constant) and isinstance(n.value, (int, float)) and not isinstance(n.value, bool):
        return _num(n.value)
    if isinstance(n, ast.Name) and n.id in VARIABLES:
        return ("var", VARIABLES.index(n.id))
    if isinstance(n, ast.Name) and n.id in CONSTANTS:
        return _num(CONSTANTS[n.id])
    if isinstance(n, ast.UnaryOp) and isinstance(n.op, (ast.USub, ast.UAdd)):
        a = _node(n.operand, logic)
        return _make("neg", a) if isinstance(n.op, ast.USub) else a
    if isinstance(n, ast.BinOp) and type(n.op) in _BINARY:
        return _make(_BINARY[type(n.op)], _node(n.left, logic), _node(n.right, logic))
    if (isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in FUNCS and len(n.args) == 1
            and not n.keywords):
        a = _node(n.args[0], logic)
        if a[0] == "num":
            return _num(numpy_value(("call", n.func.id, a), ()))
        return ("call", n.func.id, a)
    what = n.id if isinstance(n, ast.Name) else ast.unparse(n) if hasattr(ast, "unparse") else type(n).__name__
    raise ExprError(f"'{what}' is not allowed: {allowed}")


def axes_used(t: tuple) -> set[int]:
    """The axes (0: x, 1: y, 2: z) a tree reads."""
    if t[0] == "var":
        return {t[1]}
    return set().union(*(axes_used(c) for c in t[1:] if isinstance(c, tuple)))


def functions_used(t: tuple) -> set[str]:
    """The functions (``sin``, ``step``, …) a tree calls."""
    own = {t[1]} if t[0] == "call" else set()
    return own.union(*(functions_used(c) for c in t[1:] if isinstance(c, tuple)))


def derivative(t: tuple, a: int) -> tuple:
    """∂t/∂x_a, symbolically (chain rule; |u|' = sign(u) u')."""
    op, m = t[0], _make
    if op == "num":
        return _num(0)
    if op == "var":
        return _num(1.0 if t[1] == a else 0.0)
    if op == "neg":
        return m("neg", derivative(t[1], a))
    if op in ("add", "sub"):
        return m(op, derivative(t[1], a), derivative(t[2], a))
    if op == "call":
        return _call_derivative(t, a)
    u, du = t[1], derivative(t[1], a)
    if op == "mul":
        return m("add", m("mul", du, t[2]), m("mul", u, derivative(t[2], a)))
    if op == "div":
        return m("div", m("sub", m("mul", du, t[2]), m("mul", u, derivative(t[2], a))), m("pow", t[2], _num(2)))
    if op == "pow":
        v, dv = t[2], derivative(t[2], a)
        if v[0] == "num":  # c u^(c-1) u'
            return m("mul", m("mul", v, m("pow", u, _num(v[1] - 1))), du)
        return m("mul", t, m("add", m("mul", dv, ("call", "log", u)), m("div", m("mul", v, du), u)))
    raise AssertionError(op)


def _call_derivative(t: tuple, a: int) -> tuple:
    """∂/∂x_a of ``f(u)``: f'(u) u'."""
    m, u = _make, t[2]
    inner = {"sin": ("call", "cos", u), "cos": m("neg", ("call", "sin", u)), "exp": t,
             "tan": m("div", _num(1), m("pow", ("call", "cos", u), _num(2))), "log": m("div", _num(1), u),
             "sqrt": m("div", _num(0.5), t), "abs": ("call", "sign", u),
             "tanh": m("sub", _num(1), m("pow", t, _num(2))),
             "atan": m("div", _num(1), m("add", _num(1), m("pow", u, _num(2)))), "step": _num(0)}[t[1]]
    return m("mul", inner, derivative(u, a))


_NUMPY = {"sin": np.sin, "cos": np.cos, "tan": np.tan, "exp": np.exp, "log": np.log, "sqrt": np.sqrt,
          "abs": np.abs, "tanh": np.tanh, "atan": np.arctan, "sign": np.sign,
          "step": lambda u: np.where(np.asarray(u) >= 0, 1.0, 0.0)}


def numpy_value(t: tuple, x: tuple) -> Any:
    """The tree on NumPy arrays ``x = (x, y, z)`` (as many as the grid has axes; broadcast)."""
    op = t[0]
    if op == "num":
        return t[1]
    if op == "var":
        return x[t[1]]
    if op == "neg":
        return -numpy_value(t[1], x)
    if op == "not":
        return ~truth(numpy_value(t[1], x))
    with np.errstate(all="ignore"):  # callers check that the result is finite
        if op == "call":
            return _NUMPY[t[1]](numpy_value(t[2], x))
        u, v = numpy_value(t[1], x), numpy_value(t[2], x)
        return {"add": np.add, "sub": np.subtract, "mul": np.multiply, "div": np.divide, "pow": np.power,
                "lt": np.less, "le": np.less_equal, "gt": np.greater, "ge": np.greater_equal,
                "and": lambda a, b: truth(a) & truth(b), "or": lambda a, b: truth(a) | truth(b)}[op](u, v)


def truth(value: Any) -> np.ndarray:
    """A condition's value as booleans: true where nonzero and not NaN (0/0 is never true)."""
    v = np.asarray(value, dtype=np.float64)
    return (v != 0) & ~np.isnan(v)


class TaichiValue:
    """:func:`taichi_value` as a callable Taichi's compiler accepts from a ``ti.func`` without its
    "non-taichi function" warning: the walk runs once, while the kernel is traced, building the
    formula's arithmetic from the coordinates (Taichi expressions) it is given."""

    _is_taichi_function = False  # read by Taichi 1.7.4's ast_transformer: not external Python, not a ti.func

    def __call__(self, t: tuple, x: list, real) -> Any:
        import taichi as ti

        op = t[0]
        if op == "num":
            return ti.cast(t[1], real)
        if op == "var":
            return x[t[1]]
        if op == "neg":
            return -self(t[1], x, real)
        if op == "call":
            u = self(t[2], x, real)
            f = {"sin": ti.sin, "cos": ti.cos, "tan": ti.tan, "exp": ti.exp, "log": ti.log, "sqrt": ti.sqrt,
                 "abs": ti.abs, "tanh": ti.tanh, "sign": ti.math.sign,
                 "atan": lambda w: ti.atan2(w, ti.cast(1.0, real)),
                 "step": lambda w: ti.select(w >= 0, ti.cast(1.0, real), ti.cast(0.0, real))}[t[1]]
            return f(u)
        u = self(t[1], x, real)
        if op == "pow" and t[2][0] == "num" and float(t[2][1]).is_integer() and abs(t[2][1]) <= 64:
            return u ** int(t[2][1])  # integer powers by multiplication, exact for negative bases
        v = self(t[2], x, real)
        return {"add": lambda: u + v, "sub": lambda: u - v, "mul": lambda: u * v, "div": lambda: u / v,
                "pow": lambda: u ** v}[op]()


taichi_value = TaichiValue()


# ---------------------------------------------------------------------------------------
# the external potential U (units of k_B T)
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Potential:
    r"""The external potential ``U(x)`` in units of k_BT (stationary density ∝ exp(−U)), from a
    formula or, in the Python API, a NumPy-vectorised callable ``U(x, y, z)`` (as many arguments
    as axes). ``tree`` is the formula's (None for a callable); ``source`` what the scene file
    shows. A callable has no Taichi form: the particles' drift −½∇U then comes from a table of
    its central differences on a lattice finer than the grid (``methods.particles.Walker``).

    Parsed once, in ``scene.load`` (``scene.grid.potential``), and passed along as this object:
    what is derived from it (cell values, gradients, the FV scheme's weights on a grid) is made
    once, by :meth:`derived`, and kept with it (not pickled: a worker makes its own).
    """

    source: str
    dim: int
    tree: tuple | None = None
    function: Callable | None = None

    def __post_init__(self):
        object.__setattr__(self, "_made", {})  # what derived made, by key (not a field: no eq, hash or asdict)

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_made"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, _made={})

    def derived(self, key: tuple, make: Callable[[], Any]) -> Any:
        """``make()`` made once for ``key`` (say ``("cell_values", cells, lengths, pad)``), then kept:
        every reader gets the same value (an array read-only)."""
        if key not in self._made:
            value = make()
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            self._made[key] = value
        return self._made[key]

    @classmethod
    def of(cls, value: Any, dim: int) -> "Potential | None":
        """The potential of a scene's ``potential`` value (formula text, callable, or ""/None: none)."""
        if value is None or (isinstance(value, str) and not value.strip()):
            return None
        if callable(value):
            return cls(f"callable {getattr(value, '__qualname__', type(value).__name__)}", dim, function=value)
        tree = parse(value)
        extra = sorted(a for a in axes_used(tree) if a >= dim)
        if extra:
            raise ExprError(f"{value!r} uses {VARIABLES[extra[0]]} but the grid is {dim}D: "
                            f"use {', '.join(VARIABLES[:dim])}")
        return cls(value, dim, tree=tree)

    def __call__(self, *x: np.ndarray) -> np.ndarray:
        """U on NumPy coordinate arrays (one per axis, broadcast), float64."""
        u = self.function(*x) if self.function is not None else numpy_value(self.tree, x)
        return np.asarray(np.broadcast_to(u, np.broadcast_shapes(*(np.shape(a) for a in x))), dtype=np.float64)

    def gradient_trees(self) -> tuple[tuple, ...]:
        """∂U/∂x_a for every axis (formulas only; differentiated once)."""
        return self.derived(("gradient_trees",), lambda: tuple(derivative(self.tree, a) for a in range(self.dim)))

    def cell_values(self, cells: tuple[int, ...], lengths: tuple[float, ...], pad: int = 0) -> np.ndarray:
        r"""``Ū_I = −ln(⟨e^{−U}⟩_I)``: the potential whose Boltzmann factor is the cell average of
        e^{−U} (Gauss–Legendre, :data:`QUADRATURE` points per axis), on the grid grown by ``pad``
        cells beyond each side (reservoir cells). The finite-volume drift uses these values, so its
        stationary state is the cell-averaged Boltzmann profile; taken relative to the cell-centre
        value, so that a large U does not underflow. Made once per grid and ``pad`` (read-only)."""
        return self.derived(("cell_values", tuple(cells), tuple(lengths), pad),
                            lambda: self._cell_values(cells, lengths, pad))

    def _cell_values(self, cells: tuple[int, ...], lengths: tuple[float, ...], pad: int) -> np.ndarray:
        """:meth:`cell_values`, made (the quadrature)."""
        nodes, weights = np.polynomial.legendre.leggauss(QUADRATURE[len(cells)])
        h = [L / n for L, n in zip(lengths, cells)]
        centres = [(np.arange(-pad, n + pad) + 0.5) * hh for n, hh in zip(cells, h)]
        grid = np.meshgrid(*centres, indexing="ij", sparse=True)
        u0 = self(*grid)
        total = np.zeros(u0.shape)
        for idx in np.ndindex(*(len(nodes),) * len(cells)):
            pts = [g + 0.5 * hh * nodes[i] for g, hh, i in zip(grid, h, idx)]
            w = math.prod(0.5 * weights[i] for i in idx)
            with np.errstate(over="ignore", invalid="ignore"):
                total += w * np.exp(u0 - self(*pts))
        with np.errstate(divide="ignore", invalid="ignore"):
            return u0 - np.log(total)

    def boltzmann_weights(self, cells: tuple[int, ...], lengths: tuple[float, ...]) -> np.ndarray:
        """Each cell's share of ∫ e^{−U} over the domain (sums to 1)."""
        ubar = self.cell_values(cells, lengths)
        w = np.exp(-(ubar - ubar.min()))
        return w / w.sum()

    def axis_profiles(self, cells: tuple[int, ...], lengths: tuple[float, ...], sub: int) -> np.ndarray:
        r"""``(*cells, dim, sub + 1)``: in each cell and along each axis ``a``, the potential of the
        Boltzmann factor's marginal ``−ln ⟨e^{−U}⟩_⊥`` (the average over the cell's other axes,
        Gauss–Legendre) at the ``sub + 1`` evenly spaced points ``x_a = (i_a + k/sub) Δx_a`` from
        the lower face to the upper one, less the cell's :meth:`cell_values`. The hybrid places
        the particles it samples in a cell along these (``hybrid.ghosts.Sampler``): at
        equilibrium they then lie as e^{−U} does within the cell, its curvature included."""
        dim = len(cells)
        nodes, weights = np.polynomial.legendre.leggauss(QUADRATURE[dim])
        h = [L / n for L, n in zip(lengths, cells)]
        centres = [(np.arange(n) + 0.5) * hh for n, hh in zip(cells, h)]
        ubar = self.cell_values(cells, lengths)
        out = np.empty((*cells, dim, sub + 1))
        for a in range(dim):
            others = [b for b in range(dim) if b != a]
            for k in range(sub + 1):
                axes = [centres[b] if b != a else np.arange(cells[a]) * h[a] + k / sub * h[a] for b in range(dim)]
                grid = np.meshgrid(*axes, indexing="ij", sparse=True)
                u0 = self(*grid)
                total = np.zeros(u0.shape)
                for idx in np.ndindex(*(len(nodes),) * len(others)):
                    pts = list(grid)
                    for b, i in zip(others, idx):
                        pts[b] = grid[b] + 0.5 * h[b] * nodes[i]
                    w = math.prod(0.5 * weights[i] for i in idx)
                    with np.errstate(over="ignore", invalid="ignore"):
                        total += w * np.exp(u0 - self(*pts))
                with np.errstate(divide="ignore", invalid="ignore"):
                    out[..., a, k] = u0 - np.log(total) - ubar
        return out
