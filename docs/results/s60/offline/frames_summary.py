import json,sys,numpy as np
from gridmerge.transforms import corner_error
from gridmerge.bench.metrics import halmstad_point_error
rows=[json.loads(l) for f in sys.argv[1:] for l in open(f) if l.startswith('{')]
def err(r,m):
    if r['T'] is not None: return corner_error(m,np.array(r['T']),r['bshape'])
    return halmstad_point_error(m,np.array(r['pa']),np.array(r['pb']))
def cut_move(r,m,M):  # on the crop's corners ~ use cbshape
    return corner_error(m,M,r['cbshape'])
CAP=4.0
def variant(r,name):
    M,A,B=(np.array(r[k]) for k in 'MAB')
    fa = r['res'][0] < r['res'][1] or (r['res'][0] == r['res'][1] and r['ref_a'])
    pick={'ref':A if r['ref_a'] else B,'a':A,'b':B,'finer':A if fa else B,'coarser':B if fa else A}
    if name in pick and not name.endswith('_alone'):
        P=pick[name]
        if cut_move(r,P,M)>CAP: return M
        return (M+P)/2
    if name=='both3':
        ok=[P for P in (A,B) if cut_move(r,P,M)<=CAP]
        return (M+sum(ok))/(1+len(ok))
    if name=='both2':
        ok=[P for P in (A,B) if cut_move(r,P,M)<=CAP]
        return M if not ok else (M+sum(ok)/len(ok))/2
    if name=='e0': return M
    if name.endswith('_alone'):
        P=pick[name[:-6]]
        return M if cut_move(r,P,M)>CAP else P
e0=np.array([err(r,np.array(r['M'])) for r in rows]); thr=np.array([r['thr'] for r in rows])
print(len(rows))
for name in ('e0','ref','a','b','finer','coarser','both3','both2','a_alone','finer_alone'):
    e=np.array([err(r,variant(r,name)) for r in rows])
    print('%-8s precise %d right %d gain %d loss %d median %.3f mean %.3f'%(name,(e<=2).sum(),(e<=thr).sum(),((e0>2)&(e<=2)).sum(),((e0<=2)&(e>2)).sum(),np.median(e),np.minimum(e,50).mean()))
