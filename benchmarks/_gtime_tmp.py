import sys, time, warnings, numpy as np
sys.path.insert(0,'tests')
variant = sys.argv[1]
import nebula_rt.kernel_source as ks
orig = ks.read_kernel_file.__wrapped__
def patched(name):
    s = orig(name)
    if name == "transport.cl":
        if variant in ("noatomic", "none"):
            old = """    if (home)
        NRT_ATOMIC_ADD_U32_LOCAL(&lhist[b], 1u);
    else
        NRT_ATOMIC_ADD_U64(&hist[b], 1UL);"""
            assert old in s
            s = s.replace(old, "    (void)home; (void)lhist; (void)hist; (void)b;")
        if variant in ("nojt", "none"):
            s = s.replace("    float depth = t->window[(nrt_u32)t->cx[ix] + (nrt_u32)cy[iy] + (nrt_u32)cy[ny + iz]];", "    float depth = 0.0f; (void)cy;")
    return s
ks.read_kernel_file = patched
ks.kernel_source.cache_clear()
from slab_scene import slab, peel_bins
from nebula_rt.backends import get_backend
from nebula_rt.transport import trace
warnings.simplefilter("ignore")
be=get_backend("cuda","")
for tau in (10.0, 30.0):
    rho,bands,stars,kappa,cam=slab(tau,albedo=0.6,g=0.6)
    kw=dict(tau=kappa,backend=be,method="biased",peel=cam,peel_bins=peel_bins(cam))
    trace(rho,bands,stars,photons=10000,**kw)
    ks_=[]
    for i in range(4):
        r=trace(rho,bands,stars,photons=1000000,seed=1+i,**kw); ks_.append(r.timings['kernel_s'])
    print(variant, tau, 'kernel ms', np.round(np.array(ks_)*1e3,1))
