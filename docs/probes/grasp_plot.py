# The first-grasp picture of docs/policy_results.md (docs/figures/rollout_waypoint_grasps.png):
# `python grasp_plot.py <rollout out dir> <rollout out dir> <png>` with the readers venv
# (mcap, mcap-ros2-support, pillow); the two dirs are `labrig rollout --out` directories.
import sys, glob, json, math
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from PIL import Image, ImageDraw, ImageFont
def grasps(d):
    out=[]
    for p in sorted(glob.glob(d+'/rollouts/*/*/*/episode_0.mcap')):
        steps=[]; obj=None
        with open(p,'rb') as f:
            r=make_reader(f, decoder_factories=[DecoderFactory()])
            for m in r.iter_metadata():
                for k,v in m.metadata.items():
                    if 'object_position' in v:
                        try:
                            x=json.loads(v); s=x.get('sim_scene',x)
                            if isinstance(s,str): s=json.loads(s)
                            obj=s['object_position']
                        except Exception: pass
            for sch,ch,msg,dec in r.iter_decoded_messages(topics=['/rig/step']):
                steps.append((list(dec.robot_state.cartesian_position[:3]), dec.action.gripper_position))
        c=next((i for i in range(1,len(steps)) if steps[i][1]>0.5 and steps[i-1][1]<=0.5),None)
        if c is not None and obj: out.append((obj[:2], steps[c][0][:2]))
    return out
runs=[(a, grasps(d)) for a,d in [('w1 (waypoint head), step 5500',sys.argv[1]),('w2 (+ x, y hidden), step 4500',sys.argv[2])]]
W,H=1000,560; img=Image.new('RGB',(W,H),'white'); dr=ImageDraw.Draw(img)
font=ImageFont.truetype('/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf',16) 
small=ImageFont.truetype('/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf',12)
dr.text((20,10),'Where the gripper first closed (arrow head) against the cube (square), seeds 1000..1009, top view',fill='black',font=font)
# x in [0.25,0.65] up, y in [-0.35,0.35] left
def panel(ox, title, pts):
    pw,ph=460,460; x0,y0=ox,60
    dr.rectangle([x0,y0,x0+pw,y0+ph],outline='gray')
    dr.text((x0+5,y0+5),title,fill='black',font=font)
    def px(p):
        x,y=p; return (x0+(0.3-y)/0.6*pw, y0+(0.75-x)/0.6*ph)
    for i in range(7):
        gx=0.2+0.1*i
        if gx<0.75:
            a=px((gx,0.3)); b=px((gx,-0.3)); dr.line([a,b],fill=(230,230,230)); dr.text((x0+pw-48,a[1]-14),f'x {gx:.1f}',fill='gray',font=small)
    for (o,g) in pts:
        a=px(o); b=px(g); s=0.025/0.6*pw
        dr.rectangle([a[0]-s,a[1]-s,a[0]+s,a[1]+s],outline=(40,90,200),width=2)
        d=1000*math.hypot(o[0]-g[0],o[1]-g[1])
        dr.line([a,b],fill=(200,50,40),width=2); dr.ellipse([b[0]-4,b[1]-4,b[0]+4,b[1]+4],fill=(200,50,40))
        dr.text((b[0]+6,b[1]-6),f'{d:.0f}',fill=(120,30,20),font=small)
    dr.text((x0+5,y0+ph-20),'robot base below; y to the left; squares are 5 cm cubes to scale; mm',fill='gray',font=small)
for k,(t,p) in enumerate(runs): panel(20+k*490, t, p)
img.save(sys.argv[3]); print([len(p) for _,p in runs])
