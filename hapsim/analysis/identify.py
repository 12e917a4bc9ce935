"""Identification of the modes of a sampled free response (matrix pencil).

This is the measuring half of the closed-THS check (docs/design.md, 'Identification'): the
mock device (or a real one) records the position samples ``y[n]`` of the free closed loop; the poles
of the loop are identified from ``y`` alone and converted to modes (``s = ln(z)/T``,
``k = m |s|^2``, ``b = -2 m Re(s)``) to be compared with the prediction of
:func:`hapsim.analysis.loop.render`.

The poles come from the matrix pencil (:mod:`hapsim.analysis.pencil`, Hua & Sarkar 1990);
:func:`measure_felt` refines them by variable projection (the felt pair with its stated
uncertainty) and :func:`fit_free_response` fits one record.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.cycles import more_cycles_hint, seconds_above
from hapsim.analysis.modes import mode_from_pole, modes_from_poles, rendered_pair
from hapsim.analysis.pencil import pencil_poles, thin_pencil
from hapsim.errors import ConfigError

__all__ = ["measure_felt", "sensor_sd", "fit_free_response", "pair_noise_sensitivity",
           "refit_modes"]


# ------------------------------------------------------------------ noisy / quantised records
#
# A quantised or noisy record defeats a matrix pencil of the full order: the fast modes of
# the delay line and the hold are below the sensor's floor after a few samples, the SVD
# truncation keeps noise directions instead, and the "least damped pair" among the poles
# returned is then a spurious one (k = 2124 N/m for a predicted 507 on the mock with a
# 17.6 um encoder, issue of the firmware engineer). The measurement below fits only the
# modes that stand above the floor (the felt pair and any slow mode of the scene), plus the
# offset, by variable projection (Golub & Pereyra, "The differentiation of pseudo-inverses
# and nonlinear least squares problems whose variables separate", SIAM J. Numer. Anal.
# 10(2), 1973): the poles are the nonlinear parameters, the amplitudes and the offset are
# eliminated by linear least squares at every step. The standard errors are those of
# nonlinear least squares (residual variance times (J^T J)^-1, J the Jacobian of the
# model in all its parameters at the solution; Seber & Wild, *Nonlinear Regression*, 1989,
# Sec. 2.1), and the floor that the sensor implies is the same sensitivity times the
# sensor's variance: q^2 / 12 for a uniform quantiser of step q (Widrow & Kollar,
# *Quantization Noise*, 2008, ch. 4) plus the Gaussian noise variance.

#: Rounding-level residual (relative to the record's amplitude) under which a full-order
#: pencil is taken as exact: a noise-free linear record is reproduced to ~1e-13.
EXACT_RESIDUAL = 1e-9
#: Coverage factor of the stated interval, in standard errors: over random quantised or
#: noisy loops (tests/test_identify_quantised.py) error / standard error has an rms ~1.1 (k),
#: ~1.2 (b), the quantiser's error not white at a few steps: 3.5, not the Gaussian 3.
COVERAGE = 3.5
#: Least number of oscillation cycles above the floor for a measurement.
MIN_CYCLES = 1.5
#: Least initial amplitude of the felt oscillation, in sensor steps (the quantum, or the
#: noise / residual standard deviation when larger).
MIN_QUANTA = 5.0


def sensor_sd(quantum: float = 0.0, noise: float = 0.0) -> float:
    """Standard deviation of a position sensor's error [m].

    Parameters
    ----------
    quantum : float >= 0
        Quantisation step q [m] (0: none).
    noise : float >= 0
        Standard deviation of additive Gaussian noise [m].

    Returns
    -------
    float
        ``sqrt(q^2 / 12 + noise^2)``: a rounding quantiser's error is uniform over one step
        (Widrow & Kollar, *Quantization Noise*, 2008, ch. 4), independent of the noise.
    """
    return math.sqrt(float(quantum) ** 2 / 12.0 + float(noise) ** 2)


def _spec(poles) -> list:
    """Nonlinear parameters of a pole set: ``("pair", a, w)`` with ``z = exp(-a + i w)``,
    ``w > 0``, one per conjugate pair; ``("real", p)`` with ``z = p``."""
    out = []
    for z in poles:
        z = complex(z)
        if abs(z.imag) > 1e-12 * max(abs(z), 1e-300):
            if z.imag > 0:
                out.append(["pair", -math.log(abs(z)), math.atan2(z.imag, z.real)])
        else:
            out.append(["real", z.real])
    return out


def _basis(spec, theta, n, offset: bool, derivatives: bool = True):
    """Model columns Phi (n, p) and their derivatives per nonlinear parameter
    (``derivatives=False``: ``dcols`` is None, as the residual alone needs)."""
    t = np.arange(n, dtype=float)
    cols, dcols, i = [], [], 0
    for kind, *_ in spec:
        if kind == "pair":
            a, w = theta[i], theta[i + 1]
            e = np.exp(-a * t)
            c, s = e * np.cos(w * t), e * np.sin(w * t)
            cols += [c, s]
            if derivatives:
                # d/da and d/dw of c and s
                dcols.append(((len(cols) - 2, -t * c), (len(cols) - 1, -t * s)))
                dcols.append(((len(cols) - 2, -t * s), (len(cols) - 1, t * c)))
            i += 2
        else:
            p = theta[i]
            cols.append(np.power(p, t))
            if derivatives:
                dp = np.zeros(n)
                if p != 0:
                    dp[1:] = t[1:] * np.power(p, t[1:] - 1)
                dcols.append(((len(cols) - 1, dp),))
            i += 1
    if offset:
        cols.append(np.ones(n))
    return np.column_stack(cols), (dcols if derivatives else None)


def _theta(spec) -> np.ndarray:
    return np.array([v for s in spec for v in s[1:]], dtype=float)


def _bounds(n: int, lens) -> list:
    """(begin, end) of each stretch of a record of ``n`` samples cut into ``lens``."""
    if lens is None:
        return [(0, n)]
    e = np.concatenate([[0], np.cumsum(np.asarray(lens, dtype=np.int64))])
    if e[-1] != n:
        raise ValueError(f"stretch lengths {list(lens)} do not add up to {n} samples")
    return [(int(a), int(b)) for a, b in zip(e[:-1], e[1:])]


def _solve(spec, theta, y, offset, lens=None, derivatives=True):
    """Fit the linear coefficients of each stretch (its own initial condition) for the
    poles ``theta``; ``(blocks, r)`` with ``blocks`` a list of ``(phi, dcols, c)`` per
    stretch and ``r`` the residual of the whole record (``derivatives``: as
    :func:`_basis`)."""
    blocks, res = [], []
    for a, b in _bounds(y.size, lens):
        yb = y[a:b]
        with np.errstate(over="ignore", invalid="ignore"):
            phi, dcols = _basis(spec, theta, yb.size, offset, derivatives)
        if not (np.all(np.isfinite(phi)) and np.all(np.isfinite(yb))):
            # a trial pole growing past the float range: what lstsq raises on it, without
            # LAPACK first printing its complaint on stdout (into a --json report)
            raise np.linalg.LinAlgError("SVD did not converge in Linear Least Squares")
        c, *_ = np.linalg.lstsq(phi, yb, rcond=None)
        blocks.append((phi, dcols, c))
        res.append(phi @ c - yb)
    return blocks, np.concatenate(res) if res else np.zeros(0)


def _layout(spec, n: int, lens=None) -> tuple:
    """The kernel's description of the modes and stretches: ``(kinds, starts, ends)``
    (:func:`hapsim.kernels.varpro.projected`)."""
    kinds = np.array([0 if s[0] == "pair" else 1 for s in spec], dtype=np.int64)
    se = np.array(_bounds(n, lens), dtype=np.int64).reshape(-1, 2)
    return kinds, np.ascontiguousarray(se[:, 0]), np.ascontiguousarray(se[:, 1])


def _compiled(which, spec, theta, y, offset, lens=None, layout=None):
    """The projected residual (``which`` "residual", shape (n,)) or its Jacobian
    ("jacobian", shape (n, p)) at ``theta``, compiled
    (:func:`hapsim.kernels.varpro.projected`; :func:`_solve`'s mathematics: Golub &
    Pereyra 1973). ``layout``: :func:`_layout`'s, made once by a caller that evaluates
    many ``theta`` (``y`` then contiguous float64).

    Raises
    ------
    numpy.linalg.LinAlgError
        A column or the record not finite (what ``lstsq`` raises on it).
    """
    from hapsim.kernels.varpro import projected
    if layout is None:
        y = np.ascontiguousarray(y, dtype=float)
        layout = _layout(spec, y.size, lens)
    kinds, starts, ends = layout
    th = np.ascontiguousarray(theta, dtype=float)
    jac = which == "jacobian"
    out = np.empty((y.size, th.size if jac else 1))
    if not projected(kinds, th, y, starts, ends, bool(offset), jac, out):
        raise np.linalg.LinAlgError("SVD did not converge in Linear Least Squares")
    return out if jac else out[:, 0]


def _varpro(spec, y, offset, lens=None):
    """Refine the poles of ``spec`` on ``y`` by variable projection; (spec, cost).

    Levenberg-Marquardt on the projected residual with its Jacobian in closed form, both
    compiled (:func:`_compiled`): one SVD per stretch and evaluation, where a
    finite-difference Jacobian solved the least squares once per parameter (~100 for
    string.yaml's 51 modes: 26 CPU-s a measurement).
    """
    from hapsim.analysis.lm import levenberg_marquardt

    theta0 = _theta(spec)
    scale = float(np.max(np.abs(y))) or 1.0
    ys = np.ascontiguousarray(np.asarray(y, dtype=float) / scale)
    layout = _layout(spec, ys.size, lens)

    def res(th):
        return _compiled("residual", spec, th, ys, offset, layout=layout)

    def jac(th):
        return _compiled("jacobian", spec, th, ys, offset, layout=layout)

    try:
        # least_squares(method="lm", x_scale="jac")'s iterates bit for bit, without its
        # bookkeeping (a fifth of a fit's time; tests/test_identify_varpro_minpack.py)
        th = levenberg_marquardt(res, jac, theta0, tol=1e-14,
                                 max_nfev=200 * (theta0.size + 1)).x
    except (ValueError, np.linalg.LinAlgError):
        th = theta0
    out = _spec_at(spec, th)
    cost = float(np.sum(res(_theta(out)) ** 2)) * scale * scale
    return out, cost


def _spec_at(spec, th):
    """``spec``'s modes with the nonlinear parameters ``th`` (:func:`_theta`'s order), a
    pair's frequency taken positive."""
    out, i = [], 0
    for kind, *_ in spec:
        if kind == "pair":
            out.append(["pair", th[i], abs(th[i + 1])])
            i += 2
        else:
            out.append(["real", th[i]])
            i += 1
    return out


def _covariance(spec, y, offset, response=None, lens=None, proj=None):
    """Residual rms, unit covariances of the nonlinear parameters and the fitted linear
    coefficients (a list, one array per stretch). The covariances: ``(white, coloured)``;
    white = the nonlinear block of ``(J^T J)^-1`` (J over all parameters, every stretch's
    linear ones included), i.e. ``(Jt^T Jt)^-1`` with ``Jt`` the nonlinear columns
    projected off each stretch's linear ones (Schur complement; Golub & Pereyra, "The
    differentiation of pseudo-inverses and nonlinear least squares problems whose
    variables separate", SIAM J. Numer. Anal. 10(2), 1973); coloured = the sandwich with
    the filter ``response`` applied stretch by stretch (None: the white one). An error
    before a stretch reaches it as a free response of the loop, which the stretch's own
    initial condition absorbs: the filter starts again at every stretch. ``proj``:
    :func:`_projection` of the same ``spec``, ``y``, ``offset`` and ``lens``, made once by
    a caller that asks for several covariances of one fit."""
    p = _theta(spec).size
    r, jts, G, n_lin, cs, inv = (proj if proj is not None
                                 else _projection(spec, y, offset, lens))
    dof = max(y.size - p - n_lin, 1)
    col = inv
    if response is not None:
        from hapsim.analysis.fftconv import fftconvolve
        h = np.asarray(response, dtype=float)
        S = np.zeros((p, p))
        for Jt in jts:
            L = Jt.shape[0]
            FtJ = fftconvolve(Jt[::-1], h[:L, None], axes=0)[:L][::-1]   # F^T Jt
            S += FtJ.T @ FtJ
        col = inv @ S @ inv
    return (float(np.sqrt(np.sum(r * r) / dof)), (inv, col), cs)


def _projection(spec, y, offset, lens=None):
    """:func:`_projected`'s ``(r, jts, G, n_lin, cs)`` and ``pinv(G)``: what every
    covariance of one fit (:func:`_covariance`, the wire's shares in :func:`_with_wire`,
    :func:`_bounded_share`) is made from, the same arrays for each (a fit's covariances
    made it once each: three to five times a measurement)."""
    r, jts, G, n_lin, cs = _projected(spec, y, offset, lens)
    return r, jts, G, n_lin, cs, np.linalg.pinv(G)


def _projected(spec, y, offset, lens=None):
    """The fit's Jacobian in the nonlinear parameters, projected off each stretch's
    linear columns: ``(r, jts, G, n_lin, cs)`` with ``r`` the residual, ``jts`` the
    projected blocks (one per stretch, shape (L, p)), ``G = sum Jt' Jt`` (p, p), ``n_lin``
    the linear coefficients in all and ``cs`` their values per stretch."""
    theta = _theta(spec)
    p = theta.size
    blocks, r = _solve(spec, theta, y, offset, lens)
    G = np.zeros((p, p))
    jts = []
    n_lin = 0
    for phi, dcols, c in blocks:
        J = np.empty((phi.shape[0], p))
        for j, parts in enumerate(dcols):
            J[:, j] = sum(c[col] * d for col, d in parts)
        Jt = J - phi @ np.linalg.lstsq(phi, J, rcond=None)[0]
        G += Jt.T @ Jt
        jts.append(Jt)
        n_lin += phi.shape[1]
    return r, jts, G, n_lin, [c for _, _, c in blocks]


def _mode_of(spec_item, mass, period):
    kind, a, w = spec_item
    return mode_from_pole(complex(math.exp(-a) * math.cos(w), math.exp(-a) * math.sin(w)),
                          mass, period, "pair")


def measure_felt(y, period: float, mass: float, predicted, felt, *, offset: bool = False,
                 quantum: float = 0.0, noise: float = 0.0, order: int | None = None,
                 pencil: int | None = None, sensor_response=None, wire=None,
                 lens=None, bounded=None, late_bounded=None, fit=None) -> dict:
    """Felt (k, b) of a logged free response with its standard error, robust to a
    quantised or noisy position sensor; of one stretch, or of several that share the
    loop's poles, each from its own initial condition (``lens``).

    1. **Exact record** (no sensor error declared): the matrix pencil of the full order
       (:func:`pencil_poles`); if its modes reproduce the record to :data:`EXACT_RESIDUAL`
       of its amplitude, its pair nearest the predicted felt pole ``felt`` is the
       measurement (round-off accurate), not its least damped pair (a virtual mass may add
       a less damped pair with a small residue at the port).
    2. **Otherwise**: the predicted modes that fall below the sensor floor within a fifth of
       the record are dropped together with the samples they live in; the felt pair, any
       slower mode and the offset are fitted by variable projection (module notes above),
       started from the prediction, from a matrix pencil of that low order on the kept
       window and from the spectrum's peak; the start of lowest residual wins. The felt
       pair is the one that started at the predicted felt pole.

    Parameters
    ----------
    y : array_like of float, shape (n,)
        Positions [m], one per sample period, from the start of the free response (the
        stretches of ``lens`` one after the other).
    period : float > 0
        Sample period T [s].
    mass : float > 0
        Real mass m [kg] (``k = m |s|^2``, ``b = -2 m Re s``, docs/design.md,
        'The inverse map').
    predicted : array_like of complex, shape (M,)
        Predicted non-zero closed-loop poles seen at the port (conjugates included).
    felt : complex
        The predicted felt pole (upper half plane), one of ``predicted``.
    offset : bool
        The response settles away from 0 (a constant is fitted / differenced out).
    quantum, noise : float >= 0
        Sensor step q [m] and Gaussian noise standard deviation [m] (:func:`sensor_sd`).
    order, pencil : int, optional
        Order and pencil parameter of the exact path (default ``len(predicted)``).
    sensor_response : array_like of float, shape (n_h,), optional
        Impulse response from the sensor error to the logged position (``[1, 0, ...]``
        when the error is only observed; :func:`sensor_error_response` when the loop also
        feeds it back through the virtual (K, B)). The sensor's share of the covariance is
        then ``sigma_e^2 (J^T J)^-1 J^T F F^T J (J^T J)^-1`` with F the (lower triangular
        Toeplitz) filter matrix: the least-squares covariance under coloured noise
        (Seber & Wild 1989, Sec. 2.1.4). Default: white (observed only).
    wire : sequence of (float, array_like), optional
        Errors of the wire's number format, each ``(sd, response)``: a standard deviation
        (bounding the format's rounding: ``u |v|_max / sqrt(3)`` for a rounding of relative
        size at most ``u``, uniform; ``s / sqrt(12)`` for a step ``s``) and its impulse
        response to the logged position. They do not make the record noisy for the choice
        of path (a float32 record is exact to its rounding), but the stated half-interval
        covers them: ``k_sd_wire = sqrt(sum sd_i^2 g' S_i g)`` with ``S_i`` the coloured
        covariance of ``response_i`` (as the sensor's).
    lens : sequence of int, optional
        Lengths of the stretches ``y`` is made of (default: one). Each is a free response
        of the same loop from its own initial state (a record cut at gaps or a recovery):
        the poles are fitted to all of them at once, each stretch with its own linear
        coefficients (variable projection with a block-diagonal basis; Golub & Pereyra
        1973), so the whole record measures the pair. The exact path takes its poles from
        the pencil of the longest stretch and keeps them when they reproduce every
        stretch; the robust path drops its ``skipped`` samples at the start of every
        stretch, and leaves out a stretch shorter than twice its own coefficients + 4.
    bounded : sequence of (array_like, array_like), optional
        Errors bounded at given rows, each ``(e, response)``: ``e`` shape (n,), the largest
        error of each row of ``y`` [m] (0 where none: an estimated sample's position,
        :func:`hapsim.analysis.measurement.estimated_bounds`), and its impulse response to
        the logged position. Not random: their worst case, ``sum_j e_j |s_j|`` with ``s_j``
        the fit's first-order sensitivity to a unit error at row ``j`` through
        ``response``, is added to ``k_unc``, ``b_unc`` (``k_bound_rows``,
        ``b_bound_rows``).
    late_bounded : sequence of (array_like, array_like), optional
        As ``bounded``, for the error of the late ticks' accounted forces (each row's
        largest force error [N] through the force response): its worst case through the
        same first-order sensitivity is returned apart, ``k_bound_late``,
        ``b_bound_late`` [N/m, N s/m], not added to ``k_unc``, ``b_unc`` (a caller that
        decides a side on it adds it: :func:`hapsim.analysis.zwidth.record_side`).
    fit : dict, optional
        Filled by the robust path with its fitted modes (``spec``: ``["pair", a, w]``,
        ``z = exp(-a + i w)``, or ``["real", p]``) and the ``(begin, end)`` of ``y`` fitted.

    Returns
    -------
    dict
        ``k`` [N/m], ``b`` [N s/m], ``f0_hz``, ``damping_ratio``; ``k_sd``, ``b_sd``: the
        standard errors from the residual covariance; ``k_sd_sensor``, ``b_sd_sensor``:
        those the sensor's variance implies through the same sensitivity; ``k_unc``,
        ``b_unc``: the stated half-interval, :data:`COVERAGE` times the larger of the two;
        ``method`` (``"pencil"`` or ``"varpro"``), ``skipped`` (samples dropped at the
        start), ``model_order``, ``rms_residual`` [m], ``amplitude`` [m] (felt oscillation
        at the window start; the largest stretch's), ``cycles`` (oscillation cycles above
        the floor, over the stretches), ``stretches`` (the stretches fitted). Or
        ``error`` (str) when the record cannot support a measurement: the oscillation
        below :data:`MIN_QUANTA` sensor steps, or fewer than :data:`MIN_CYCLES` cycles above
        that level, or the record is constant (``at_rest`` True: the loop never moved).

    Raises
    ------
    ConfigError
        Invalid ``period``, ``mass``, a non-finite or too short signal.
    """
    if not (np.isfinite(mass) and mass > 0):
        raise ConfigError(f"must be a positive number [kg], got {mass!r}", key="mass")
    y = np.asarray(y, dtype=float)
    predicted = np.asarray(predicted, dtype=complex)
    floor = sensor_sd(quantum, noise)
    order = int(order if order is not None else predicted.size)
    amp0 = float(np.max(np.abs(y - (np.median(y[-max(y.size // 10, 1):]) if offset else 0.0))))
    bounds = _bounds(y.size, lens)
    lens = [b - a for a, b in bounds]
    la, lb = max(bounds, key=lambda ab: ab[1] - ab[0])      # the longest stretch
    if y.size and np.all(np.isfinite(y)) and amp0 == 0.0:
        # a loop at rest (no excitation, or x0 = 0 on the rest position): a valid record
        # with nothing in it to identify (and log(0) below)
        return {"error": "the record is constant: the loop never moved (a scene at rest; "
                         "give it an excitation: x0, v0, impulse or profile)",
                "at_rest": True, "amplitude": 0.0}
    if floor == 0.0:
        md = None
        try:
            z = pencil_poles(y[la:lb], order, offset=offset, period=period,
                             pencil=pencil or thin_pencil(order, lb - la - int(offset)))
        except ConfigError:
            z = None
        if z is not None and np.all(np.isfinite(z)):
            spec = _spec(z[np.abs(z) > 0])
            try:
                proj = _projection(spec, y, offset, lens)
                rms, cov, _ = _covariance(spec, y, offset, None, lens, proj)
            except np.linalg.LinAlgError:
                # a pencil pole growing past the float range over a stretch (not the
                # loop's free response exactly; once out of a loaded Hapkit run's report):
                # no exact fit, the robust path below measures it
                rms = math.inf
            md = rendered_pair(modes_from_poles(z, mass, period))
            if md is not None and rms <= EXACT_RESIDUAL * amp0:
                # the identified pair at the predicted felt pole, not the least damped one:
                # a virtual mass adds pairs the hand barely feels (they have a small
                # residue at the port) and one of them may be less damped
                zf = complex(felt) if complex(felt).imag >= 0 else complex(felt).conjugate()
                fi = min((i for i, s in enumerate(spec) if s[0] == "pair"),
                         key=lambda i: abs(_mode_of(spec[i], mass, period).z - zf))
                out = _with_wire(_result(spec, fi, cov, rms, 0.0, mass, period, y, offset,
                                         method="pencil", skipped=0, lens=lens),
                                 spec, fi, y, offset, wire, mass, period, lens, bounded,
                                 late_bounded, proj)
                out["record_amplitude"] = amp0
                return out
    # ---- robust path
    felt = complex(felt)
    if felt.imag < 0:
        felt = felt.conjugate()
    n = lb - la
    rho = max(floor, 1e-12 * amp0) / max(amp0, 1e-300) / 10.0
    skip, keep = 0, []
    for z in predicted:
        az = abs(z)
        if abs(z - felt) <= 1e-12 * abs(felt) or abs(z - felt.conjugate()) <= 1e-12 * abs(felt):
            keep.append(z)
            continue
        if az < abs(felt) and az > 0:
            nz = math.log(rho) / math.log(az) if az < 1 else math.inf
            if nz <= n / 5:
                skip = max(skip, int(math.ceil(nz)))
                continue
        keep.append(z)
    spec0 = _spec(keep)
    n_lin = sum(2 if sp_[0] == "pair" else 1 for sp_ in spec0) + int(offset)
    kept = [(a + skip, b) for a, b in bounds
            if b - a - skip >= 2 * n_lin + 4 or (a, b) == (la, lb)]
    yw = np.concatenate([y[a:b] for a, b in kept])
    lens_w = [b - a for a, b in kept]
    yl = y[la + skip:lb]                 # the longest stretch's window
    fi = min((i for i, s in enumerate(spec0) if s[0] == "pair"),
             key=lambda i: abs(_mode_of(spec0[i], mass, period).z - felt))
    starts = [spec0]
    try:        # the pencil of the kept order on the window, matched to the prediction
        zp = pencil_poles(yl, len(keep), offset=offset, period=period,
                          pencil=thin_pencil(len(keep), yl.size - int(offset)))
        sp = _spec(zp)
        if [s[0] for s in sorted(sp)] == [s[0] for s in sorted(spec0)]:
            pairs = [s for s in sp if s[0] == "pair"]
            reals = sorted((s for s in sp if s[0] == "real"), key=lambda s: s[1])
            cand, used = [], set()
            for s in spec0:
                if s[0] == "pair":
                    j = min((j for j in range(len(pairs)) if j not in used),
                            key=lambda j: abs(pairs[j][2] - s[2]) + abs(pairs[j][1] - s[1]))
                    used.add(j)
                    cand.append(list(pairs[j]))
                else:
                    cand.append(list(reals.pop(0)))
            starts.append(cand)
    except ConfigError:
        pass
    yc = yl - np.mean(yl)          # the spectrum's peak: frequency of the felt pair
    nfft = 1 << int(math.ceil(math.log2(max(8 * yc.size, 64))))
    spec_mag = np.abs(np.fft.rfft(yc, nfft))
    spec_mag[0] = 0.0
    wpk = 2 * math.pi * int(np.argmax(spec_mag)) / nfft
    if wpk > 0:
        alt = [list(s) for s in spec0]
        alt[fi][2] = wpk
        starts.append(alt)
    best = None
    for st in starts:
        sp, cost = _varpro(st, yw, offset, lens_w)
        if all(np.isfinite(_theta(sp))) and (best is None or cost < best[1]):
            best = (sp, cost)
    spec = best[0]
    try:
        proj = _projection(spec, yw, offset, lens_w)
        rms, cov, c = _covariance(spec, yw, offset, sensor_response, lens_w, proj)
    except np.linalg.LinAlgError:      # (a ground 1e300 m away: a traceback out of run)
        raise ConfigError("the record's fit has no finite covariance") from None
    if fit is not None:
        fit.update(spec=[list(sp_) for sp_ in spec], kept=list(kept))
    out = _with_wire(_result(spec, fi, cov, rms, floor, mass, period, yw, offset,
                              method="varpro", skipped=skip, step=max(float(quantum), floor),
                              lens=lens_w, ends=kept[-1][1] == bounds[-1][1], record_amp=amp0),
                      spec, fi, yw, offset, wire, mass, period, lens_w,
                      None if not bounded else [
                          (np.concatenate([np.asarray(e, float)[a:b] for a, b in kept]), r)
                          for e, r in bounded],
                      None if not late_bounded else [
                          (np.concatenate([np.asarray(e, float)[a:b] for a, b in kept]), r)
                          for e, r in late_bounded], proj)
    out["record_amplitude"] = amp0
    return out


def _bounded_share(spec, fi, y, offset, bounded, mass, period, lens=None, proj=None):
    """Worst-case (k, b) error of bounded errors at given rows (:func:`measure_felt`'s
    ``bounded``): ``sum_j e_j |s_j|`` with ``s_j = sum_m S_(j+m) h_m`` the fit's first-order
    response to a unit error at row ``j`` filtered by ``h`` (``S = g' (J'J)^-1 J'``, the
    linearised least-squares estimate's sensitivity to the record; Seber & Wild 1989,
    Sec. 2.1), its nonlinear rows ``g' (Jt'Jt)^-1 Jt'`` with ``Jt`` projected off each
    stretch's linear columns; the filter starts again at every stretch of ``lens``.
    ``proj``: :func:`_projection`'s, as :func:`_covariance` takes it."""
    from hapsim.analysis.fftconv import fftconvolve
    n = y.size
    _, jts, G, _, _, A = proj if proj is not None else _projection(spec, y, offset, lens)
    i = sum(2 if s[0] == "pair" else 1 for s in spec[:fi])
    g_k, g_b = _kb_gradients(spec, fi, i, mass=mass, period=period)
    bounds = _bounds(n, lens)
    S_k = np.concatenate([g_k @ A @ Jt.T for Jt in jts])
    S_b = np.concatenate([g_b @ A @ Jt.T for Jt in jts])
    bk = bb = 0.0
    for e, resp in bounded:
        e = np.asarray(e, float)[:n]
        if e.size < n:
            e = np.concatenate([e, np.zeros(n - e.size)])
        if not np.any(e > 0):
            continue
        r = np.asarray(resp, float)
        for S, acc in ((S_k, "k"), (S_b, "b")):
            sj = np.zeros(n)
            for a, b in bounds:
                L = b - a
                h = np.zeros(L)
                h[:min(L, r.size)] = r[:L]
                sj[a:b] = fftconvolve(S[a:b][::-1], h)[:L][::-1]
            v = float(np.sum(e * np.abs(sj)))
            if acc == "k":
                bk += v
            else:
                bb += v
    return bk, bb


def _with_wire(out, spec, fi, y, offset, wire, mass, period, lens=None, bounded=None,
               late_bounded=None, proj=None):
    """``out`` with the wire's share of the uncertainty (:func:`measure_felt`'s ``wire``):
    ``k_sd_wire``, ``b_sd_wire``, and ``k_unc``, ``b_unc`` covering them too; with
    ``bounded``, the worst case of those errors (``k_bound_rows``, ``b_bound_rows``) added
    to ``k_unc``, ``b_unc``; with ``late_bounded``, theirs (``k_bound_late``,
    ``b_bound_late``) apart. ``proj``: the fit's :func:`_projection`, made once."""
    if late_bounded and "k" in out:
        out["k_bound_late"], out["b_bound_late"] = _bounded_share(
            spec, fi, y, offset, late_bounded, mass, period, lens, proj)
    if bounded and "k" in out:
        bk, bb = _bounded_share(spec, fi, y, offset, bounded, mass, period, lens, proj)
        out["k_bound_rows"], out["b_bound_rows"] = bk, bb
        out["k_unc"] += bk
        out["b_unc"] += bb
    if not wire:
        return out
    i = sum(2 if s[0] == "pair" else 1 for s in spec[:fi])
    g_k, g_b = _kb_gradients(spec, fi, i, mass=mass, period=period)
    vk = vb = 0.0
    for sd, resp in wire:
        if not sd > 0:
            continue
        _, (_, col), _ = _covariance(spec, y, offset, resp, lens, proj)
        vk += sd * sd * max(float(g_k @ col @ g_k), 0.0)
        vb += sd * sd * max(float(g_b @ col @ g_b), 0.0)
    out["k_sd_wire"], out["b_sd_wire"] = math.sqrt(vk), math.sqrt(vb)
    bk, bb = out.get("k_bound_rows", 0.0), out.get("b_bound_rows", 0.0)
    out["k_unc"] = max(out["k_unc"], COVERAGE * out["k_sd_wire"] + bk)
    out["b_unc"] = max(out["b_unc"], COVERAGE * out["b_sd_wire"] + bb)
    return out


def _kb_gradients(spec, fi, i, *, mass, period):
    """Gradients of ``k = m (sigma^2 + omega^2)`` and ``b = 2 m sigma``
    (docs/design.md, 'The inverse map'; ``sigma = a / T``, ``omega = w / T``) over the
    nonlinear parameters of ``spec``; the pair ``spec[fi]`` has its ``(a, w)`` at index
    ``i``."""
    n = sum(2 if s[0] == "pair" else 1 for s in spec)
    sig, om = spec[fi][1] / period, spec[fi][2] / period
    g_k, g_b = np.zeros(n), np.zeros(n)
    g_k[i], g_k[i + 1] = 2 * mass * sig / period, 2 * mass * om / period
    g_b[i] = 2 * mass / period
    return g_k, g_b


def refit_modes(spec, y, lens, *, mass: float, period: float, offset: bool,
                felt: complex) -> dict | None:
    """The felt pair of a record refitted with given modes: :func:`measure_felt`'s
    robust path's variable projection started from ``spec`` alone, on windows it chose
    already (the draws of :mod:`hapsim.analysis.pair_rounding`, each the run's record
    rounded another way: the run's fit from the exact motion's minimum).

    Parameters
    ----------
    spec : list
        Modes (``["pair", a, w]``, ``z = exp(-a + i w)``, or ``["real", p]``) to start
        from.
    y : ndarray, shape (n,)
        The windows' positions one after the other [m].
    lens : sequence of int
        The windows' lengths.
    mass, period : float
        m [kg] and T [s] (``k = m |s|^2``, ``b = -2 m Re s``).
    offset : bool
        A constant is fitted.
    felt : complex
        The predicted felt pole: the pair nearest it in ``spec`` is the felt one.

    Returns
    -------
    dict or None
        ``spec`` (the refined modes), ``k`` [N/m], ``b`` [N s/m]; None when the fit
        gives no finite pair.
    """
    pairs = [i for i, s in enumerate(spec) if s[0] == "pair"]
    if not pairs:
        return None
    zf = complex(felt) if complex(felt).imag >= 0 else complex(felt).conjugate()
    fi = min(pairs, key=lambda i: abs(_mode_of(spec[i], mass, period).z - zf))
    try:
        sp, _ = _varpro([list(s) for s in spec], np.asarray(y, float), offset, list(lens))
        md = _mode_of(sp[fi], mass, period)
    except (ValueError, OverflowError, np.linalg.LinAlgError):
        return None
    if not (math.isfinite(md.k) and math.isfinite(md.b) and sp[fi][2] > 0):
        return None
    return {"spec": sp, "k": float(md.k), "b": float(md.b)}


def pair_noise_sensitivity(y, period: float, mass: float, sigma: float,
                           omega: float) -> tuple[float, float]:
    """Standard deviations of the felt (k, b) that :func:`measure_felt`'s least-squares fit
    of one damped pair plus an offset gives per unit of white observation noise.

    The fit's covariance is ``s^2 (Jt^T Jt)^-1`` over the pair's nonlinear parameters
    ``(a, w) = (sigma T, omega T)``, the linear ones (amplitudes, offset) projected out
    (Golub & Pereyra, SIAM J. Numer. Anal. 10(2), 1973); ``k = m (sigma^2 + omega^2)`` and
    ``b = 2 m sigma`` (docs/design.md, 'The inverse map') carry it to first order.

    Parameters
    ----------
    y : ndarray, shape (n,)
        The noise-free record the fit sees [m] (its amplitudes set the Jacobian).
    period : float
        Sample period T [s].
    mass : float
        m [kg].
    sigma, omega : float
        The pair's decay rate [1/s] and angular frequency [rad/s].

    Returns
    -------
    (float, float)
        ``(sd_k, sd_b)`` per metre of noise standard deviation [N/m per m], [N s/m per m].
    """
    spec = [["pair", sigma * period, omega * period]]
    _, (white, _), _ = _covariance(spec, np.asarray(y, float), True)
    g_k, g_b = _kb_gradients(spec, 0, 0, mass=mass, period=period)
    return (float(np.sqrt(max(g_k @ white @ g_k, 0.0))),
            float(np.sqrt(max(g_b @ white @ g_b, 0.0))))


def _result(spec, fi, cov, rms, floor, mass, period, y, offset, *, method, skipped,
            step=0.0, lens=None, ends=True, record_amp=math.inf):
    """The measurement dict of :func:`measure_felt` for the pair ``spec[fi]`` (over the
    stretches ``lens`` of ``y``: the amplitude is the largest stretch's, the cycles above
    the floor are summed over the stretches). ``record_amp``: the record's largest
    excursion from rest [m]: one inside the floor's band holds no oscillation above it."""
    md = _mode_of(spec[fi], mass, period)
    i = sum(2 if s[0] == "pair" else 1 for s in spec[:fi])
    sig = spec[fi][1] / period
    g_k, g_b = _kb_gradients(spec, fi, i, mass=mass, period=period)
    white, coloured = cov

    def sd(g, c):
        return float(np.sqrt(max(g @ c @ g, 0.0)))
    _, _, cs = _covariance(spec, y, offset, None, lens)
    # a pair has 2 nonlinear and 2 linear parameters (per stretch)
    amps = [float(math.hypot(c[i], c[i + 1])) for c in cs]
    ns = [b - a for a, b in _bounds(y.size, lens)]
    amp = max(amps)
    out = {"k": float(md.k), "b": float(md.b), "f0_hz": float(md.f0_hz),
           "damping_ratio": float(md.damping_ratio), "k_sd": rms * sd(g_k, white),
           "b_sd": rms * sd(g_b, white), "k_sd_sensor": floor * sd(g_k, coloured),
           "b_sd_sensor": floor * sd(g_b, coloured),
           "method": method, "skipped": int(skipped),
           "model_order": sum(2 if s[0] == "pair" else 1 for s in spec),
           "rms_residual": rms, "amplitude": amp, "stretches": len(ns)}
    out["k_unc"] = COVERAGE * max(out["k_sd"], out["k_sd_sensor"])
    out["b_unc"] = COVERAGE * max(out["b_sd"], out["b_sd_sensor"])
    fl = max(step, rms) if method == "varpro" else 0.0
    if fl > 0:
        hz = md.f0_hz * math.sqrt(max(1 - md.damping_ratio ** 2, 0))
        level = MIN_QUANTA * fl
        out["cycles"] = float(hz * sum(seconds_above(amps, ns, sig, level, period)))
        # the floor is the sensor's (its quantum or noise) or, when the fit leaves more,
        # the fit's residual: said as what it is (a record with no sensor floor that the
        # model does not fit is not the predicted loop's response, not a short one)
        if rms > step:
            fit = f"{MIN_QUANTA:g} x the {method} fit's rms residual ({fl:.3g} m"
            what = (f"{fit}; the sensor's step is {step:.3g} m)" if step > 0 else
                    f"{fit}; the sensor has no quantum or noise: the record is not the "
                    f"order-{out['model_order']} linear loop's response, an input the "
                    f"account does not know acted)")
        else:
            what = f"{MIN_QUANTA:g} sensor steps of {fl:.3g} m (the quantum or the noise)"
        if record_amp < MIN_QUANTA * fl:
            # (a fit's cancelling modes may give its pair 10^3..10^6 m there: "1.6e-07
            # cycles above", on the Haply joint started at 0.002 rad, test_rotary_units)
            out["error"] = (f"the record's largest excursion from rest ({record_amp:.3g} m) "
                            f"is below {what}: no measurement")
        elif amp < MIN_QUANTA * fl:
            out["error"] = (f"the oscillation ({amp:.3g} m at the window start) is below "
                            f"{what}: no measurement")
        elif out["cycles"] < MIN_CYCLES:
            shown = float(f"{out['cycles']:.2g}")
            if shown >= MIN_CYCLES:     # (1.47 cycles read "1.5", the count needed)
                shown = math.floor(out["cycles"] * 10.0) / 10.0
            out["error"] = (f"only {shown:g} oscillation cycles above "
                            f"{what}: too few for a measurement"
                            + more_cycles_hint(amps, ns, sig, level, period, hz, MIN_CYCLES,
                                               rms <= step, ends_record=ends))
    else:
        out["cycles"] = float(md.f0_hz * y.size * period)
    return out


def fit_free_response(position, period: float, mass: float, k_guess: float,
                      b_guess: float) -> dict:
    """Felt (k, b) of a logged free response with an offset: :func:`measure_felt` on its
    dominant pair, started from a guess.

    Parameters
    ----------
    position : ndarray, shape (n,)
        Positions [m], one per period, from the start of the free response (the loop's
        fast modes already decayed: this model has only the pair and the offset).
    period : float
        Sample period T [s].
    mass : float
        m [kg].
    k_guess, b_guess : float
        Starting point [N/m], [N s/m] (the prediction).

    Returns
    -------
    dict
        :func:`measure_felt`'s result plus ``samples``; ``rms_residual`` [m].

    Raises
    ------
    ConfigError
        As :func:`measure_felt`; also when the guess is not an oscillation
        (``k_guess / m <= (b_guess / 2 m)^2``).
    """
    sig = b_guess / (2.0 * mass)
    om2 = k_guess / mass - sig * sig
    if not om2 > 0:
        raise ConfigError(f"the guess (k, b) = ({k_guess!r}, {b_guess!r}) is not an "
                          "oscillation", key="k_guess")
    z = complex(np.exp(complex(-sig, math.sqrt(om2)) * period))
    out = measure_felt(position, period, mass, [z, z.conjugate()], z, offset=True)
    out["samples"] = int(np.asarray(position).size)
    return out
