import sys, time, json
import numpy as np
sys.path.insert(0, ".")
from bench.vs_lammps import scene_spec
from engine.params import derive
from engine.scene import initial_spheres
from engine.simulate import contact_params
from engine.shapes.sphere.cpu_backend import CpuBackend
n = int(sys.argv[2]); phi = 0.008 if n <= 4096 else 0.058
spec = scene_spec(n, phi, 10000)
p = derive(spec)
be = CpuBackend(initial_spheres(spec, p), contact_params(spec, p, thermalization=False))
be.warmup(); be.advance(2000)
steps = max(200, int(4e7 // n))
rates = []
for _ in range(7):
    t = time.perf_counter(); be.advance(steps); rates.append(n * steps / (time.perf_counter() - t))
print(json.dumps(dict(side=sys.argv[1], n=n, best=max(rates), median=float(np.median(rates)))), flush=True)
