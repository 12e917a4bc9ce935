"""Blind identification on the mock: seeded random devices, coverage of the reported intervals.

Usage: PYTHONPATH=. python tools/identify_blind.py [SEED] [N] [DURATION_S]
Prints each miss (and every noise-free case) and the misses per quantity. A benchmark-style
program, not a test: the coverage it prints is what docs/identify.md states.
"""
import time, numpy as np, sys
from hapsim.scene import Device
from hapsim.daemon.identify_run import record
from hapsim.analysis.device_fit import fit_device
rng = np.random.default_rng(int(sys.argv[1]) if len(sys.argv)>1 else 12)
N = int(sys.argv[2]) if len(sys.argv)>2 else 50
dur = float(sys.argv[3]) if len(sys.argv)>3 else 3.0
miss = {}
t0=time.time()
for i in range(N):
    m = float(np.exp(rng.uniform(np.log(0.02), 0)))
    b = float(rng.uniform(0,5)); fc=float(rng.uniform(0,0.3)); d=int(rng.integers(0,4))
    q = float(rng.uniform(0,20e-6)) if rng.random()<0.7 else 0.0
    nz = float(rng.uniform(0,5e-6)) if rng.random()<0.7 else 0.0
    dev = Device(mass=m, friction=b, delay=d, coulomb=fc, position_resolution=q, noise=nz, force_limit=10.0)
    rec = record(dev, transport="inprocess", duration=dur, force_limit=4.0, progress=False, handle_signals=False, seed=i, noise_seed=i)
    fit = fit_device(rec["position"], rec["force"], rec["period"], late=rec["late"])
    checks = {"m": fit.mass.contains(m), "b0": fit.friction.contains(b), "fc+": fit.coulomb_pos.contains(fc),
              "fc-": fit.coulomb_neg.contains(fc), "d": fit.delay_range[0] <= d <= fit.delay_range[1] and fit.hold=="zoh",
              "q": fit.position_resolution.contains(q), "noise": fit.noise.contains(nz)}
    bad = [k for k,v in checks.items() if not v]
    for k in bad: miss[k] = miss.get(k,0)+1
    rel = (fit.mass.value/m-1, fit.friction.value-b)
    if bad or nz==0:
        print(i, f"m={m:.3g} b={b:.3g} fc={fc:.3g} d={d} q={q:.2g} nz={nz:.2g} | m^={fit.mass.value:.4g} [{fit.mass.lo:.4g},{fit.mass.hi:.4g}] b^={fit.friction.value:.4g} [{fit.friction.lo:.4g},{fit.friction.hi:.4g}] fc^={fit.coulomb_pos.value:.3g}/{fit.coulomb_neg.value:.3g} d^={fit.delay}{fit.hold} nz^={fit.noise.value:.2g}[{fit.noise.lo:.2g},{fit.noise.hi:.2g}] rms={fit.rms_residual:.2g} {fit.explained} {rec['loop']['stop_reason']} BAD={bad}", flush=True)
print("misses", miss, "time", time.time()-t0)
