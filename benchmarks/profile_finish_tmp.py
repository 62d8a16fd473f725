import cProfile, pstats, sys, os, time
sys.path.insert(0, "benchmarks")
os.environ["NRT_BENCH_ERROR_ESTIMATE"] = sys.argv[2] if len(sys.argv) > 2 else "packets"
import bench_large_grids as b
from nebula_rt.backends import get_backend
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene
n = int(sys.argv[1])
be = get_backend("cuda", "")
Pipeline(be).run(Scene.from_dict(b.scene_dict(16, 10000, 1)), colour=False)
sc = Scene.from_dict(b.scene_dict(n, 10_000_000, 1))
pr = cProfile.Profile()
t = time.perf_counter()
pr.enable()
light = Pipeline(be).run(sc, colour=False)
pr.disable()
print(os.environ["NRT_BENCH_ERROR_ESTIMATE"], "wall", time.perf_counter() - t, light.timings)
pstats.Stats(pr).sort_stats("cumulative").print_stats(25)
