"""Phase of the command times on the 10 Hz clock grid (relative to each run's first aligned row)."""
import sys; sys.path.insert(0, 'experiments')
import numpy as np
from model_grid import load_aligned
al = load_aligned()
for rid, run in al.groupby("run_id"):
    t = run["t"].to_numpy(); m = run["matched"].to_numpy(bool)
    tc = t[m]; d = np.diff(tc)
    phase = ((tc - t[0]) * 10) % 1.0
    print(rid[-5:], "cmds", m.sum(), "interval s: median %.4f p5 %.4f p95 %.4f" % (np.median(d), *np.percentile(d, [5, 95])),
          "phase(0.1s units) mean %.2f std %.2f" % (phase.mean(), phase.std()),
          "frac intervals round(d*10)!=5: %.3f" % np.mean(np.round(d*10)!=5))
print("circular")
for rid, run in al.groupby("run_id"):
    t = run["t"].to_numpy(); m = run["matched"].to_numpy(bool)
    tc = t[m]; ph = ((tc - t[0]) * 10) % 1.0
    z = np.exp(2j*np.pi*ph); R = abs(z.mean()); mean = (np.angle(z.mean())/(2*np.pi)) % 1
    dev = ((ph - mean + 0.5) % 1) - 0.5
    print(rid[-5:], "circ mean phase %.2f, dev from mean: std %.3f, p5 %.3f p95 %.3f (x0.1 s); drift first->last quarter %.3f" % (
        mean, dev.std(), *np.percentile(dev, [5, 95]), dev[-len(dev)//4:].mean() - dev[:len(dev)//4].mean()))
