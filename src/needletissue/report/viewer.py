"""An interactive 3D view of FE results for report.html: self-contained, offline, no library.

Why a small WebGL viewer with the data embedded, not vtk.js/trame or three.js: the report must open
from a file with no network and no server (trame needs a server; vtk.js and three.js would add
0.5-1 MB of vendored script for a few draw calls), and the view needs only what a surgeon-engineer
asks of it here: the deformed anatomy and needles at each force, tissues on and off, |u| or von Mises
colours with their colour bar, the axes and the coordinate frame. The page stays a single file.

Data: each region's boundary triangles (linear corners of its tetrahedra), per region its own vertex
copies so that a cell field (von Mises) is averaged within the region only, and per force the vertex
displacements and von Mises stresses, as base64 little-endian float32 / uint32 arrays.
"""

from __future__ import annotations

import base64
import html
import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from needletissue.errors import InputError

_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])  # outward for positive tetrahedra
_COUNTER = itertools.count(1)


@dataclass
class RegionSurface:
    name: str
    points: np.ndarray            # (n, 3) mm, reference positions
    triangles: np.ndarray         # (m, 3) indices into points
    displacement: list            # per frame (n, 3) mm
    von_mises: list               # per frame (n,) MPa


@dataclass
class Scene:
    frames: list[str]                           # labels, e.g. "100 N"
    regions: list[RegionSurface]
    frame_of_reference: str = "LPS"             # coordinate frame of the points (DICOM patient LPS or model)
    hidden: tuple[str, ...] = ()                # regions off at start
    arrow: dict | None = field(default=None)    # {"origin": [3], "direction": [3], "label": str}
    view: tuple | None = None                   # direction from the model to the eye at start


def boundary_triangles(cells: np.ndarray) -> np.ndarray:
    """Triangles (corner indices, outward) bounding a set of tetrahedra: faces used by one cell only."""
    faces = cells[:, :4][:, _FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    return faces[np.sort(first[counts == 1])]


def scene_from_vtus(paths: list, labels: list[str], region_names: dict[int, str], *,
                    frame_of_reference: str = "LPS", hidden=(), arrow=None, view=None) -> Scene:
    """A Scene from VTU files of one mesh at successive loads (point `displacement`, cell `region`
    and `von_mises_MPa`), as FEResult.write_vtu writes them."""
    import meshio

    if len(paths) != len(labels) or not paths:
        raise InputError("viewer.frames", f"need one label per VTU file, got {len(paths)} files, {len(labels)} labels")
    meshes = [meshio.read(p) for p in paths]
    m0 = meshes[0]
    block = next((i for i, c in enumerate(m0.cells) if c.type in ("tetra", "tetra10")), None)
    if block is None:
        raise InputError("viewer.mesh", f"{Path(paths[0]).name} holds no tetrahedra")
    cells = m0.cells[block].data[:, :4]
    tags = np.asarray(m0.cell_data["region"][block]).astype(int)
    regions = []
    for tag in sorted(set(tags.tolist())):
        sel = tags == tag
        tri_global = boundary_triangles(cells[sel])
        used, tri = np.unique(tri_global, return_inverse=True)
        tri = tri.reshape(-1, 3)
        # von Mises per vertex: mean of the region's cells at the vertex
        rc = cells[sel]
        local = np.full(m0.points.shape[0], -1)
        local[used] = np.arange(used.size)
        lc = local[rc]
        keep = lc >= 0
        counts = np.bincount(lc[keep], minlength=used.size).astype(float)
        disp, vm = [], []
        for m in meshes:
            vm_cells = np.asarray(m.cell_data["von_mises_MPa"][block], float)[sel]
            sums = np.bincount(lc[keep], weights=np.repeat(vm_cells, 4).reshape(-1, 4)[keep], minlength=used.size)
            vm.append(sums / np.maximum(counts, 1))
            disp.append(np.asarray(m.point_data["displacement"], float)[used])
        regions.append(RegionSurface(region_names.get(tag, f"region {tag}"), np.asarray(m0.points[used], float),
                                     tri, disp, vm))
    return Scene(list(labels), regions, frame_of_reference, tuple(hidden), arrow, view)


def model_scene(vtus: list, forces: list[float], region_tags: dict[str, int], force_direction, needle_axis, *,
                frame_of_reference: str, hidden=()) -> Scene:
    """The scene of a needle or anatomical model run: one frame per force, the force arrow at the
    clamp, seen across the needle and the force (the plane the needles bend in)."""
    scene = scene_from_vtus(vtus, [f"{f:g} N" for f in forces], {v: k for k, v in region_tags.items()},
                            frame_of_reference=frame_of_reference, hidden=hidden)
    f = np.asarray(force_direction, float) / np.linalg.norm(force_direction)
    view = np.cross(np.asarray(needle_axis, float), f)
    scene.view = tuple(view) if np.linalg.norm(view) > 1e-6 else None
    clamp = next((r for r in scene.regions if r.name == "clamp"), None)
    if clamp is not None:
        scene.arrow = {"origin": clamp.points.mean(axis=0).tolist(), "direction": f.tolist(),
                       "label": f"F = {forces[-1]:g} N"}
    return scene


def _b64(a: np.ndarray, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()).decode()


def scene_payload(scene: Scene) -> dict:
    umax = max((float(np.linalg.norm(d, axis=1).max()) for r in scene.regions for d in r.displacement
                if len(d)), default=0.0)
    vmax = max((float(v.max()) for r in scene.regions for v in r.von_mises if len(v)), default=0.0)
    return {
        "frames": scene.frames, "frame_of_reference": scene.frame_of_reference, "arrow": scene.arrow,
        "view": None if scene.view is None else (np.asarray(scene.view, float) / np.linalg.norm(scene.view)).tolist(),
        "ranges": {"u": [0.0, umax], "vm": [0.0, vmax]},
        "regions": [{"name": r.name, "visible": r.name not in scene.hidden,
                     "points": _b64(r.points, "f4"), "triangles": _b64(r.triangles, "u4"),
                     "displacement": [_b64(d, "f4") for d in r.displacement],
                     "von_mises": [_b64(v, "f4") for v in r.von_mises]} for r in scene.regions],
    }


def viewer_html(scene: Scene, title: str = "") -> str:
    """An HTML fragment (div + data + script) that draws the scene; several may share a page."""
    vid = f"ntv{next(_COUNTER)}"
    data = json.dumps(scene_payload(scene)).replace("</", "<\\/")
    return (f'<div class="ntv" id="{vid}"><div class="ntv-title">{html.escape(title)}</div>'
            f'<div class="ntv-controls"></div><div class="ntv-stage"><canvas class="ntv-gl"></canvas>'
            f'<canvas class="ntv-overlay"></canvas></div><div class="ntv-bar"><canvas class="ntv-cbar">'
            f'</canvas><span class="ntv-cbar-label"></span></div>'
            f'<noscript>The 3D view needs JavaScript and WebGL.</noscript></div>'
            f'<script type="application/json" id="{vid}-data">{data}</script>'
            f'<script>needletissueViewer("{vid}")</script>')


def page_head() -> str:
    """CSS and the viewer's script: once per page, before the first viewer_html fragment."""
    return f"<style>{_CSS}</style><script>{_JS}</script>"


def write_viewer(path, scene: Scene, title: str = "") -> Path:
    """A standalone page with one viewer."""
    from needletissue.runinfo import write_atomic

    doc = (f"<!doctype html><html><head><meta charset='utf-8'><meta name='viewport' "
           f"content='width=device-width, initial-scale=1'><title>{html.escape(title or 'needletissue 3D view')}"
           f"</title>{page_head()}</head><body>{viewer_html(scene, title)}</body></html>")
    return write_atomic(path, doc)


_CSS = """
.ntv{max-width:100%;margin:1em 0;font:14px system-ui,sans-serif}
.ntv-title{font-weight:600;margin:.3em 0}
.ntv-controls{display:flex;flex-wrap:wrap;gap:.4em 1em;align-items:center;margin:.3em 0}
.ntv-controls label{white-space:nowrap}
.ntv-stage{position:relative;width:100%;height:min(70vh,560px);background:#fafafa;border:1px solid #ccc;touch-action:none}
.ntv-stage canvas{position:absolute;left:0;top:0;width:100%;height:100%}
.ntv-overlay{pointer-events:none}
.ntv-bar{display:flex;align-items:center;gap:.6em;margin:.3em 0;flex-wrap:wrap}
.ntv-cbar{width:min(320px,70vw);height:34px}
"""

_JS = r"""
function needletissueViewer(id){
const root=document.getElementById(id), D=JSON.parse(document.getElementById(id+'-data').textContent);
const glc=root.querySelector('.ntv-gl'), ov=root.querySelector('.ntv-overlay'), ctl=root.querySelector('.ntv-controls');
const cbar=root.querySelector('.ntv-cbar'), cbl=root.querySelector('.ntv-cbar-label');
const gl=glc.getContext('webgl',{antialias:true,preserveDrawingBuffer:true});
const api={ready:false,frame:D.frames.length-1,field:'u',scale:1,drawn:0,regions:D.regions.map(r=>r.name)};
root.viewer=api;
if(!gl){root.querySelector('.ntv-stage').textContent='WebGL is not available in this browser.';return;}
gl.getExtension('OES_element_index_uint');
function dec(s,T){const b=atob(s),u=new Uint8Array(b.length);for(let i=0;i<b.length;i++)u[i]=b.charCodeAt(i);return new T(u.buffer);}
const R=D.regions.map(r=>({name:r.name,visible:r.visible,p:dec(r.points,Float32Array),t:dec(r.triangles,Uint32Array),
  u:r.displacement.map(s=>dec(s,Float32Array)),vm:r.von_mises.map(s=>dec(s,Float32Array)),
  vb:gl.createBuffer(),nb:gl.createBuffer(),cb:gl.createBuffer(),ib:gl.createBuffer()}));
let lo=[1e9,1e9,1e9],hi=[-1e9,-1e9,-1e9];
for(const r of R){for(let i=0;i<r.p.length;i++){lo[i%3]=Math.min(lo[i%3],r.p[i]);hi[i%3]=Math.max(hi[i%3],r.p[i]);}
  gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER,r.ib);gl.bufferData(gl.ELEMENT_ARRAY_BUFFER,r.t,gl.STATIC_DRAW);}
const C=[0,1,2].map(k=>(lo[k]+hi[k])/2), S=Math.max(...[0,1,2].map(k=>hi[k]-lo[k]))||1;
// viridis, 9 stops
const VIR=[[68,1,84],[71,44,122],[59,81,139],[44,113,142],[33,144,141],[39,173,129],[92,200,99],[170,220,50],[253,231,37]];
function cmap(x){x=Math.min(1,Math.max(0,x))*8;const i=Math.min(7,Math.floor(x)),f=x-i,a=VIR[i],b=VIR[i+1];
  return [0,1,2].map(k=>(a[k]+(b[k]-a[k])*f)/255);}
const vs=`attribute vec3 p;attribute vec3 n;attribute vec3 c;uniform mat4 M;uniform mat3 N;varying vec3 vc;
void main(){vec3 nn=normalize(N*n);float l=0.35+0.65*abs(nn.z);vc=c*l;gl_Position=M*vec4(p,1.0);}`;
const fs=`precision mediump float;varying vec3 vc;void main(){gl_FragColor=vec4(vc,1.0);}`;
function sh(t,s){const o=gl.createShader(t);gl.shaderSource(o,s);gl.compileShader(o);return o;}
const prog=gl.createProgram();gl.attachShader(prog,sh(gl.VERTEX_SHADER,vs));gl.attachShader(prog,sh(gl.FRAGMENT_SHADER,fs));
gl.linkProgram(prog);gl.useProgram(prog);
const A={p:gl.getAttribLocation(prog,'p'),n:gl.getAttribLocation(prog,'n'),c:gl.getAttribLocation(prog,'c')};
const U={M:gl.getUniformLocation(prog,'M'),N:gl.getUniformLocation(prog,'N')};
let yaw0=0.6,pitch0=-1.2;
// pitch < 0 keeps +z (superior in LPS) up on the screen
if(D.view){pitch0=-Math.acos(Math.max(-1,Math.min(1,D.view[2])));yaw0=Math.atan2(-D.view[0],-D.view[1]);}
let yaw=yaw0,pitch=pitch0,zoom=1;
const PAL=[[.89,.10,.11],[.22,.49,.72],[.30,.69,.29],[.60,.31,.64],[1,.50,0],[.65,.34,.16],[.97,.51,.75],[.6,.6,.6],[.1,.75,.8],[.74,.74,.13]];
function update(){const f=api.frame,rng=(D.ranges[api.field]||[0,1])[1]||1;
  R.forEach((r,ri)=>{const n=r.p.length/3,x=new Float32Array(r.p.length),nr=new Float32Array(r.p.length),col=new Float32Array(r.p.length);
    const u=r.u[f];for(let i=0;i<r.p.length;i++)x[i]=r.p[i]+api.scale*u[i];
    for(let i=0;i<n;i++){const v=api.field==='u'?Math.hypot(u[3*i],u[3*i+1],u[3*i+2]):r.vm[f][i];
      const c=api.field==='region'?PAL[ri%PAL.length]:cmap(v/rng);
      col[3*i]=c[0];col[3*i+1]=c[1];col[3*i+2]=c[2];}
    const t=r.t;for(let k=0;k<t.length;k+=3){const a=3*t[k],b=3*t[k+1],c=3*t[k+2];
      const e1=[x[b]-x[a],x[b+1]-x[a+1],x[b+2]-x[a+2]],e2=[x[c]-x[a],x[c+1]-x[a+1],x[c+2]-x[a+2]];
      const q=[e1[1]*e2[2]-e1[2]*e2[1],e1[2]*e2[0]-e1[0]*e2[2],e1[0]*e2[1]-e1[1]*e2[0]];
      for(const v of [a,b,c]){nr[v]+=q[0];nr[v+1]+=q[1];nr[v+2]+=q[2];}}
    gl.bindBuffer(gl.ARRAY_BUFFER,r.vb);gl.bufferData(gl.ARRAY_BUFFER,x,gl.DYNAMIC_DRAW);
    gl.bindBuffer(gl.ARRAY_BUFFER,r.nb);gl.bufferData(gl.ARRAY_BUFFER,nr,gl.DYNAMIC_DRAW);
    gl.bindBuffer(gl.ARRAY_BUFFER,r.cb);gl.bufferData(gl.ARRAY_BUFFER,col,gl.DYNAMIC_DRAW);});
  colorbar();draw();}
function rot(){const cy=Math.cos(yaw),sy=Math.sin(yaw),cp=Math.cos(pitch),sp=Math.sin(pitch);
  // rotate about z (yaw), then about x (pitch): rows of the 3x3 view rotation
  return [[cy,-sy,0],[cp*sy,cp*cy,-sp],[sp*sy,sp*cy,cp]];}
function draw(){const w=glc.clientWidth,h=glc.clientHeight,dpr=window.devicePixelRatio||1;
  for(const c of [glc,ov]){c.width=Math.max(1,Math.round(w*dpr));c.height=Math.max(1,Math.round(h*dpr));}
  gl.viewport(0,0,glc.width,glc.height);gl.clearColor(0.98,0.98,0.98,1);gl.enable(gl.DEPTH_TEST);
  gl.clear(gl.COLOR_BUFFER_BIT|gl.DEPTH_BUFFER_BIT);
  const Rm=rot(),s=2*zoom/S,asp=w/Math.max(h,1),sx=asp>1?s/asp:s,sy=asp>1?s:s*asp;
  const M=new Float32Array(16);for(let i=0;i<3;i++){M[i*4+0]=Rm[0][i]*sx;M[i*4+1]=Rm[1][i]*sy;M[i*4+2]=-Rm[2][i]/S;}  // depth independent of zoom: always inside the clip range
  M[12]=-(Rm[0][0]*C[0]+Rm[0][1]*C[1]+Rm[0][2]*C[2])*sx;M[13]=-(Rm[1][0]*C[0]+Rm[1][1]*C[1]+Rm[1][2]*C[2])*sy;
  M[14]=(Rm[2][0]*C[0]+Rm[2][1]*C[1]+Rm[2][2]*C[2])/S;M[15]=1;
  const N=new Float32Array([Rm[0][0],Rm[1][0],Rm[2][0],Rm[0][1],Rm[1][1],Rm[2][1],Rm[0][2],Rm[1][2],Rm[2][2]]);
  gl.uniformMatrix4fv(U.M,false,M);gl.uniformMatrix3fv(U.N,false,N);api.drawn=0;
  for(const r of R){if(!r.visible)continue;
    for(const [b,a] of [[r.vb,A.p],[r.nb,A.n],[r.cb,A.c]]){gl.bindBuffer(gl.ARRAY_BUFFER,b);gl.enableVertexAttribArray(a);gl.vertexAttribPointer(a,3,gl.FLOAT,false,0,0);}
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER,r.ib);gl.drawElements(gl.TRIANGLES,r.t.length,gl.UNSIGNED_INT,0);api.drawn+=r.t.length/3;}
  overlay(Rm,w,h,dpr);}
function overlay(Rm,w,h,dpr){const g=ov.getContext('2d');g.setTransform(dpr,0,0,dpr,0,0);g.clearRect(0,0,w,h);
  const o=[44,h-44],L=30,names=D.frame_of_reference==='LPS'?['x (L)','y (P)','z (S)']:['x','y','z'],cols=['#c00','#080','#00c'];
  g.font='12px system-ui,sans-serif';g.lineWidth=2;
  for(let k=0;k<3;k++){const dx=Rm[0][k]*L,dy=-Rm[1][k]*L;g.strokeStyle=cols[k];g.fillStyle=cols[k];
    g.beginPath();g.moveTo(o[0],o[1]);g.lineTo(o[0]+dx,o[1]+dy);g.stroke();g.fillText(names[k],o[0]+dx*1.25-8,o[1]+dy*1.25+4);}
  g.fillStyle='#333';g.fillText(D.frame_of_reference+' mm; '+D.frames[api.frame]+'; deformation x'+api.scale,8,16);
  if(D.arrow){const a=D.arrow,p=proj(a.origin,Rm,w,h),q=proj(a.origin.map((v,k)=>v+a.direction[k]*S*0.25),Rm,w,h);
    g.strokeStyle='#d40';g.fillStyle='#d40';g.lineWidth=3;g.beginPath();g.moveTo(p[0],p[1]);g.lineTo(q[0],q[1]);g.stroke();
    const ang=Math.atan2(q[1]-p[1],q[0]-p[0]);g.beginPath();g.moveTo(q[0],q[1]);
    g.lineTo(q[0]-12*Math.cos(ang-0.4),q[1]-12*Math.sin(ang-0.4));g.lineTo(q[0]-12*Math.cos(ang+0.4),q[1]-12*Math.sin(ang+0.4));g.fill();
    g.fillText(a.label||'force',q[0]+6,q[1]);}}
function proj(x,Rm,w,h){const s=2*zoom/S,asp=w/Math.max(h,1),sx=asp>1?s/asp:s,sy=asp>1?s:s*asp,d=[0,1,2].map(k=>x[k]-C[k]);
  const X=(Rm[0][0]*d[0]+Rm[0][1]*d[1]+Rm[0][2]*d[2])*sx,Y=(Rm[1][0]*d[0]+Rm[1][1]*d[1]+Rm[1][2]*d[2])*sy;
  return [(X+1)*w/2,(1-Y)*h/2];}
function colorbar(){if(api.field==='region'){cbar.style.display='none';
  cbl.textContent='colour: tissue (legend: the check boxes)';R.forEach((r,ri)=>{const c=PAL[ri%PAL.length];
  root.querySelector(`input[data-region="${r.name}"]`).parentNode.style.color=`rgb(${c.map(v=>Math.round(v*200)).join(',')})`;});return;}
  cbar.style.display='';root.querySelectorAll('.ntv-controls label').forEach(l=>l.style.color='');const dpr=window.devicePixelRatio||1,w=cbar.clientWidth||300,h=cbar.clientHeight||34;
  cbar.width=w*dpr;cbar.height=h*dpr;const g=cbar.getContext('2d');g.setTransform(dpr,0,0,dpr,0,0);
  for(let i=0;i<w;i++){const c=cmap(i/(w-1));g.fillStyle=`rgb(${c.map(v=>Math.round(v*255)).join(',')})`;g.fillRect(i,0,1,16);}
  const rng=D.ranges[api.field][1];g.fillStyle='#222';g.font='11px system-ui,sans-serif';
  for(const f of [0,0.5,1]){const t=(rng*f).toPrecision(3),x=Math.min(w-g.measureText(t).width,Math.max(0,f*w-g.measureText(t).width/2));g.fillText(t,x,30);}
  cbl.textContent=api.field==='u'?'|u| (mm)':'von Mises stress (MPa)';}
// controls
function sel(label,opts,val,on){const l=document.createElement('label');l.textContent=label+' ';const s=document.createElement('select');
  opts.forEach(([v,t])=>{const o=document.createElement('option');o.value=v;o.textContent=t;s.appendChild(o);});s.value=val;
  s.onchange=()=>on(s.value);l.appendChild(s);ctl.appendChild(l);return s;}
sel('load',D.frames.map((f,i)=>[i,f]),api.frame,v=>{api.frame=+v;update();});
sel('colour',[['u','|u| (mm)'],['vm','von Mises (MPa)'],['region','tissue']],'u',v=>{api.field=v;update();});
sel('deformation',[[1,'true scale'],[3,'x3'],[10,'x10']],1,v=>{api.scale=+v;update();});
R.forEach((r,i)=>{const l=document.createElement('label'),c=document.createElement('input');c.type='checkbox';c.checked=r.visible;
  c.dataset.region=r.name;c.onchange=()=>{r.visible=c.checked;draw();};l.appendChild(c);l.appendChild(document.createTextNode(' '+r.name));ctl.appendChild(l);});
const rb=document.createElement('button');rb.textContent='reset view';rb.onclick=()=>{yaw=yaw0;pitch=pitch0;zoom=1;draw();};ctl.appendChild(rb);
let drag=null;glc.addEventListener('pointerdown',e=>{drag=[e.clientX,e.clientY];glc.setPointerCapture(e.pointerId);});
glc.addEventListener('pointermove',e=>{if(!drag)return;yaw+=(e.clientX-drag[0])*0.01;pitch+=(e.clientY-drag[1])*0.01;drag=[e.clientX,e.clientY];draw();});
glc.addEventListener('pointerup',()=>{drag=null;});
glc.addEventListener('wheel',e=>{e.preventDefault();zoom*=Math.exp(-e.deltaY*0.001);draw();},{passive:false});
window.addEventListener('resize',()=>{colorbar();draw();});
api.setFrame=i=>{api.frame=i;update();};api.setField=f=>{api.field=f;update();};
api.setVisible=(name,v)=>{R.find(r=>r.name===name).visible=v;draw();};
update();api.ready=true;root.dataset.ready='1';}
"""
