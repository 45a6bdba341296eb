# list cases: imprecise-right + wrong + sample of precise, from latest sim and hm3d runs
import sys, json, random
sys.path.insert(0,'/tmp/s62'); sys.path.insert(0,'/tmp/s61')
exec(open('/tmp/s62/totals62.py').read().split("show('sim 51-131'")[0])
re[103]='g62'
def hm62b(s):
    import os
    for l in ('f62','g62'):
        d=f'{T}/{l}_hm3d_s{s}'
        if os.path.exists(d+'/cases.jsonl'): return d
    return hm62(s)
rng=random.Random(5)
out=open('/tmp/s63/cases2.jsonl','w'); n=dict(imp=0,wrong=0,ctl=0)
for kind,runs in (('sim',[sim62(s) for s in range(51,132)]),('hm3d',[hm62b(s) for s in range(39,69)])):
    for d in runs:
        for l in open(d+'/cases.jsonl'):
            c=json.loads(l)
            if c['method']!='hybrid' or not c['positive'] or not c['aligned']: continue
            err=c['corner_error_px']
            if c['precise']:
                if rng.random()>0.25: continue
                o='ctl'
            elif c['success']: o='imp'
            else: o='wrong'
            n[o]+=1
            out.write(json.dumps(dict(run=d,cid=c['case_id'],E=c['estimate']['matrix'],err=err,outcome=o,kind=kind))+'\n')
print(n)
