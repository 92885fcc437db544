"""After warm_process(spec) (the worker's standby), the first large start of spec's kind: its wall time."""
import sys, time
sys.path.insert(0, '.')
from engine.spec import SimulationSpec
from engine.params import derive
from engine.shapes import host
from engine.simulate import warm_process
n = 1 << 20
kw = dict(shape="ellipsoid", elongation=2.0, n_particles=n, volume_fraction=0.058,
          box_length=2.0 * (n / 4096) ** (1 / 3), thermalization=0)
t = time.perf_counter(); warm_process(SimulationSpec(shape="ellipsoid", elongation=2.0)); t1 = time.perf_counter()
spec = SimulationSpec(**kw); p = derive(spec)
t2 = time.perf_counter(); host("ellipsoid").initial_system(spec, p); t3 = time.perf_counter()
host("ellipsoid").initial_system(spec, p); t4 = time.perf_counter()
print(f"warm_process {t1-t:.3f} s; first rough-ellipsoid 2^20 start {t3-t2:.3f} s, second {t4-t3:.3f} s")
