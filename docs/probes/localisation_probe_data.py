# Probe data for docs/probes/localisation_probe.py (issue 32 diagnosis): per approach step of
# each demo (every step until the gripper command first changes; every other one after step
# 2), the wrist and ext1 JPEGs as recorded (128x128) and the grasp point relative to the TCP.
# Run with ~/.cache/labrig/venv-readers/bin/python (mcap, mcap-ros2-support, numpy).
import sys, glob, numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
# the successful demos of `labrig demo --first-seed 0` and `--first-seed 100` (100 each), in
# this order: the first 175 train the probe, the last 20 are held out
eps = sorted(glob.glob('demo_a/episodes/success/*/*/episode_0.mcap')) + sorted(glob.glob('demo_b/episodes/success/*/*/episode_0.mcap'))
jw=[];je=[];off=[];epi=[];tt=[]
for k,p in enumerate(eps):
    steps=[];wr=[];e1=[]
    with open(p,'rb') as f:
        r=make_reader(f, decoder_factories=[DecoderFactory()])
        for sch,ch,msg,dec in r.iter_decoded_messages(topics=['/rig/step','/cameras/wrist/image/compressed','/cameras/ext1/image/compressed']):
            if ch.topic=='/rig/step': steps.append((list(dec.robot_state.cartesian_position[:3]), dec.action.gripper_position))
            elif 'wrist' in ch.topic: wr.append(bytes(dec.data))
            else: e1.append(bytes(dec.data))
    n=min(len(steps),len(wr),len(e1))
    closed=[s[1]>0.5 for s in steps]
    ev=next((i for i in range(1,len(steps)) if closed[i]!=closed[0]), len(steps)-1)
    grasp=np.array(steps[ev][0])
    for t in range(0,min(ev,n)):
        if t>2 and t%2: continue
        jw.append(np.frombuffer(wr[t],np.uint8)); je.append(np.frombuffer(e1[t],np.uint8))
        off.append(grasp-np.array(steps[t][0])); epi.append(k); tt.append(t)
    if k%20==0: print(k,len(off),flush=True)
def pack(l):
    lens=np.array([len(x) for x in l]); return np.concatenate(l), lens
w,wl=pack(jw); e,el=pack(je)
np.savez(sys.argv[1] if len(sys.argv) > 1 else 'probe.npz', wrist=w, wrist_len=wl, ext1=e, ext1_len=el, offset=np.array(off,np.float32), episode=np.array(epi), t=np.array(tt))
print(len(off), w.nbytes/1e6, e.nbytes/1e6)
