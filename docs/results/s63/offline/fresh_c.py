import sys, json, numpy as np, gridmerge, importlib
from dataclasses import replace
from multiprocessing import Pool
from gridmerge.bench import runner
from gridmerge.transforms import corner_error
AL=importlib.import_module('gridmerge.align')
def work(spec):
    run,cid,err=spec
    bench=runner.BenchRun.load(run); case=runner.rebuild_case(bench,cid)
    AL.METHODS['hybrid']=replace(AL.METHODS['hybrid'],chamfer=False)
    r=gridmerge.align(case.a,case.b,rng=0)
    e=corner_error(r.transform,np.asarray(case.truth),case.b.shape) if r.success and case.positive else None
    return run.split('/')[-1],cid[-4:],case.positive,e,err
if __name__=='__main__':
    specs=[]
    for run in sys.argv[1:]:
        for l in open(run+'/cases.jsonl'):
            c=json.loads(l)
            if c['method']=='hybrid' and 'chamfer' in (c.get('details') or {}):
                specs.append((run,c['case_id'],c.get('corner_error_px')))
    print(len(specs),'chamfer')
    with Pool(2) as p:
        for r in p.imap(work,specs): print(r, flush=True)
