import sys
sys.path.insert(0, ".")
from bench.gpu_scaling import lattice_scene
from engine.backends.cuda import CudaBackend
for prec in ("float64", "float32"):
    sy, c = lattice_scene(65536, 0.058, prec)
    be = CudaBackend(sy, c)
    be.warmup()
    be.advance(5)
    for name in ("kick_drift", "forces", "run_steps", "half_kick", "settle"):
        if name not in be.e.k:
            continue
        for sig, kern in be.e.k[name].overloads.items():
            print(sys.argv[1], prec, name, "regs", kern.regs_per_thread, "local", kern.local_mem_per_thread, flush=True)
