"""What the real runs say about the arm's structure, before any simulator is fitted.

Reads the aligned runs of ``robot=sorolex_csv`` (its align artifact, made when missing:
:func:`pipeline.studies.recorded_runs`) at 20 Hz and prints, per section:

- ``rest``: each run's rest pose (first second, at the 2 kPa preload), pressure ranges and the
  ceiling of the pressure sum;
- ``step``: the step response (mm per kPa on one chamber) of a linear FIR model (4 s of lags)
  fitted to all runs: dead time, rise time, overshoot, settled gain and direction per chamber;
- ``fir``: leave-one-run-out error of FIR models, linear in the pressures, with squares and
  products (a static nonlinearity), and with rising and falling pressure apart (asymmetry);
- ``gains``: per run, the settled gain (mm/kPa) and direction of each chamber of a linear map
  from lagged pressure, against the run's mean pressure;
- ``stiffening``: leave-one-run-out error of a static map on lagged pressures whose gain falls
  with the mean pressure, ``exp(-k (mean - 2 kPa))``, for several k;
- ``residual``: per run, the in-run error of a linear FIR fitted to that run alone and the
  spectrum of what it leaves.

Usage: ``python -m experiments.calibration_data [section ...]`` (all sections by default).
"""

from __future__ import annotations

import sys

import numpy as np

from pipeline.data.runs import Run
from pipeline.studies import recorded_runs

HZ = 20.0
REST_FRAMES = 20  # the first second


def load_runs() -> list[Run]:
    """The runs of ``robot=sorolex_csv`` at ``HZ`` on a regular grid."""
    return recorded_runs("robot=sorolex_csv", rate_hz=HZ, grid="clock")[1]


def lagged(x: np.ndarray, lags: int) -> np.ndarray:
    padded = np.concatenate([np.repeat(x[:1], lags, 0), x])
    return np.concatenate([padded[lags - k:lags - k + len(x)] for k in range(lags)], 1)


def features(p: np.ndarray, kind: str) -> np.ndarray:
    d = p.astype(np.float64) - 2.0
    if kind == "linear":
        return d
    if kind == "quadratic":
        return np.concatenate([d, d**2, d[:, [0]] * d[:, [1]], d[:, [1]] * d[:, [2]],
                               d[:, [0]] * d[:, [2]]], 1)
    if kind == "rise_fall":
        change = np.diff(np.concatenate([p[:1], p]), axis=0)
        return np.concatenate([np.cumsum(np.maximum(change, 0), 0),
                               np.cumsum(np.minimum(change, 0), 0)], 1)
    raise ValueError(kind)


def design(p: np.ndarray, kind: str, lags: int) -> np.ndarray:
    return np.concatenate([np.ones((len(p), 1)), lagged(features(p, kind), lags)], 1)


def displacement(run: Run) -> np.ndarray:
    return run.positions_m - run.positions_m[:REST_FRAMES].mean(0)


def loro_mm(runs: list[Run], make_x) -> list[float]:
    """Leave-one-run-out mean error (mm); the held-out run's rest pose is its first second."""
    errors = []
    for i, run in enumerate(runs):
        train = [r for j, r in enumerate(runs) if j != i]
        weights = np.linalg.lstsq(np.concatenate([make_x(r) for r in train]),
                                  np.concatenate([displacement(r) for r in train]), rcond=None)[0]
        predicted = make_x(run) @ weights + run.positions_m[:REST_FRAMES].mean(0)
        errors.append(1e3 * np.linalg.norm(predicted - run.positions_m, axis=1).mean())
    return errors


def lag_filter(p: np.ndarray, delay: int = 3, tau: float = 0.5) -> np.ndarray:
    """The pressure seen through a dead time (frames) and a first-order lag (s)."""
    p = np.concatenate([np.repeat(p[:1], delay, 0), p])[:len(p)].astype(np.float64)
    out, state, a = np.empty_like(p), p[0].copy(), 1.0 / (HZ * tau)
    for t in range(len(p)):
        state = state + a * (p[t] - state)
        out[t] = state
    return out


def section_rest(runs):
    print("run    rest (x, y, z) mm       p min..max kPa   sum min..max kPa   mean p kPa")
    for r in runs:
        rest, p = r.positions_m[:REST_FRAMES].mean(0) * 1e3, r.pressures_kpa
        total = p.sum(1)
        print(f"{r.run_id[-5:]}  {rest.round(1)}  {p.min():5.2f}..{p.max():4.2f}"
              f"      {total.min():4.1f}..{total.max():4.1f}         {p.mean():.2f}")


def section_step(runs, lags=80):
    x = np.concatenate([design(r.pressures_kpa, "linear", lags) for r in runs])
    weights = np.linalg.lstsq(x, np.concatenate([displacement(r) for r in runs]), rcond=None)[0]
    step = np.cumsum(weights[1:].reshape(lags, 3, 3), 0) * 1e3  # [lag, chamber, axis] mm/kPa
    print("step response to +1 kPa on one chamber, |x-z| mm (and y mm):")
    print("  t [s] " + "".join(f"   chamber {c}     " for c in range(3)))
    for k in (0, 2, 3, 4, 6, 10, 14, 20, 30, 40, 60, 79):
        cells = "".join(f"  {np.hypot(step[k, c, 0], step[k, c, 2]):5.2f} ({step[k, c, 1]:5.2f})"
                        for c in range(3))
        print(f"  {k / HZ:5.2f} {cells}")
    for c in range(3):
        final = step[-1, c]
        lateral = np.hypot(step[:, c, 0], step[:, c, 2])
        print(f"chamber {c}: settled {np.hypot(final[0], final[2]):.2f} mm/kPa toward "
              f"{np.degrees(np.arctan2(final[2], final[0])):.0f} deg (x-z), y {final[1]:.2f} "
              f"mm/kPa; 63 % at {np.argmax(lateral >= 0.63 * lateral[-1]) / HZ:.2f} s, peak/final "
              f"{lateral.max() / lateral[-1]:.2f}")


def section_fir(runs, lags=80):
    for kind in ("linear", "quadratic", "rise_fall"):
        errors = loro_mm(runs, lambda r, kind=kind: design(r.pressures_kpa, kind, lags))
        print(f"FIR {kind:9s} leave-one-run-out mean {np.mean(errors):.2f} mm, per run "
              f"{np.round(errors, 2)}")


def section_gains(runs):
    print("run    |gain| mm/kPa per chamber   direction deg     mean p kPa   sum max kPa")
    for r in runs:
        filtered = lag_filter(r.pressures_kpa)
        x = np.concatenate([np.ones((len(filtered), 1)), filtered], 1)
        gains = np.linalg.lstsq(x, r.positions_m, rcond=None)[0][1:] * 1e3  # [chamber, axis]
        # with a fixed pressure sum (the low-ceiling runs) only gain differences are identified
        pair = np.hypot(*(gains[0] - gains[1])[[0, 2]])
        print(f"{r.run_id[-5:]}  {np.hypot(gains[:, 0], gains[:, 2]).round(2)}  "
              f"{np.degrees(np.arctan2(gains[:, 2], gains[:, 0])).round(0)}   "
              f"{r.pressures_kpa.mean():.2f}        {r.pressures_kpa.sum(1).max():.1f}   "
              f"|g0 - g1| {pair:.1f}")


def section_stiffening(runs):
    filtered = {r.run_id: lag_filter(r.pressures_kpa) for r in runs}

    def make_x(run, k):
        pf = filtered[run.run_id]
        mean = pf.mean(1, keepdims=True)
        return np.concatenate([np.ones((len(pf), 1)), (pf - mean) * np.exp(-k * (mean - 2)),
                               mean - 2], 1)

    for k in (0.0, 0.2, 0.4, 0.6, 0.8, 1.0):
        errors = loro_mm(runs, lambda r, k=k: make_x(r, k))
        print(f"static map, gain exp(-{k:.1f} (mean p - 2)): leave-one-run-out "
              f"{np.mean(errors):.2f} mm, per run {np.round(errors, 2)}")


def section_residual(runs, lags=60):
    for r in runs:
        x = design(r.pressures_kpa, "linear", lags)
        residual = (x @ np.linalg.lstsq(x, r.positions_m, rcond=None)[0] - r.positions_m) * 1e3
        power = (np.abs(np.fft.rfft(residual - residual.mean(0), axis=0))**2).sum(1)
        freq = np.fft.rfftfreq(len(residual), 1 / HZ)
        share = [power[(freq >= lo) & (freq < hi)].sum() / power.sum()
                 for lo, hi in ((0, 0.05), (0.05, 0.5), (0.5, np.inf))]
        print(f"{r.run_id[-5:]}: in-run linear FIR {np.linalg.norm(residual, axis=1).mean():.2f}"
              f" mm; residual power <0.05 Hz {share[0]:.2f}, 0.05-0.5 Hz {share[1]:.2f}, "
              f">0.5 Hz {share[2]:.2f}")


SECTIONS = {"rest": section_rest, "step": section_step, "fir": section_fir,
            "gains": section_gains, "stiffening": section_stiffening,
            "residual": section_residual}

if __name__ == "__main__":
    runs = load_runs()
    for name in sys.argv[1:] or list(SECTIONS):
        print(f"== {name}")
        SECTIONS[name](runs)
