// rigbridge live view: a WebSocket client for /api/live and a small 3D renderer on a 2D
// canvas (perspective projection, painter's algorithm, orbit/zoom camera). No library and
// no build step: docs/live-view.md says why. World coordinates are metres, z up.
'use strict';

// ---------------------------------------------------------------- page health --
// What a test (or a person) reads to judge the page: first frame time, frame and message
// rates, and every error the page saw.
const health = {
  firstFrameMs: null,
  framesDrawn: 0,
  fps: 0,
  wsMessages: 0,
  wsRate: 0,
  paintQuads: 0,
  sceneWalls: 0,
  sceneCylinders: 0,
  sceneSolids: 0,
  sceneBodies: 0,
  // The cell's parts drawn, and the program's step as last shown.
  sceneParts: 0,
  programStep: '',
  // The running job's plan as drawn: tool path points and targets.
  planPoints: 0,
  planTargets: 0,
  errors: [],
};
window.rigbridgeView = health;

function recordError(text) {
  health.errors.push(String(text));
  const list = document.getElementById('errors');
  if (list) {
    const item = document.createElement('li');
    item.textContent = String(text);
    list.appendChild(item);
    document.getElementById('error-count').textContent = String(health.errors.length);
  }
}
window.addEventListener('error', (event) => {
  recordError('error: ' + event.message + ' at ' + event.filename + ':' + event.lineno);
});
window.addEventListener('unhandledrejection', (event) => {
  recordError('unhandled rejection: ' + (event.reason && event.reason.message || event.reason));
});
const consoleError = console.error.bind(console);
console.error = (...args) => {
  recordError('console.error: ' + args.map(String).join(' '));
  consoleError(...args);
};

// ---------------------------------------------------------------------- token --
// With a token, it comes from the URL fragment (#token=..., never sent to any server) or
// the form; it is kept for this tab only.
function readToken() {
  const match = /(?:^#|&)token=([^&]*)/.exec(location.hash);
  if (match) {
    sessionStorage.setItem('rigbridge-token', decodeURIComponent(match[1]));
    history.replaceState(null, '', location.pathname + location.search);
  }
  return sessionStorage.getItem('rigbridge-token') || '';
}
let token = readToken();

function authHeaders() {
  return token ? { Authorization: 'Bearer ' + token } : {};
}

function askForToken(why) {
  const form = document.getElementById('token-form');
  form.hidden = false;
  setConnection('down', why);
}

document.getElementById('token-form').addEventListener('submit', (event) => {
  event.preventDefault();
  token = document.getElementById('token-input').value.trim();
  sessionStorage.setItem('rigbridge-token', token);
  document.getElementById('token-form').hidden = true;
  connect();
  loadCells();
});

// --------------------------------------------------------------------- camera --
const canvas = document.getElementById('view');
const ctx = canvas.getContext('2d');
// The camera looks at the middle of the scene from the front left; `fitCamera` sizes it to
// the scene. Until the user moves it, it follows every new scene.
const HOME_CAMERA = { yaw: -2.25, pitch: 0.38, distance: 2.0, target: [0.25, 0.0, 0.42] };
const camera = Object.assign({}, HOME_CAMERA);
let cameraMoved = false;
let dirty = true;

function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
function cross(a, b) {
  return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
}
function normalize(a) {
  const n = Math.hypot(a[0], a[1], a[2]) || 1;
  return [a[0] / n, a[1] / n, a[2] / n];
}

// The camera's eye and basis for this draw.
function view() {
  const c = Math.cos(camera.pitch);
  const t = camera.target;
  const eye = [
    t[0] + camera.distance * c * Math.cos(camera.yaw),
    t[1] + camera.distance * c * Math.sin(camera.yaw),
    t[2] + camera.distance * Math.sin(camera.pitch),
  ];
  const forward = normalize(sub(t, eye));
  const right = normalize(cross(forward, [0, 0, 1]));
  const up = cross(right, forward);
  const focal = 0.9 * Math.min(canvas.width, canvas.height);
  return { eye, forward, right, up, focal, cx: canvas.width / 2, cy: canvas.height / 2 };
}

const NEAR = 0.05;
// Screen point [x, y, depth], or null behind the near plane.
function project(v, p) {
  const d = sub(p, v.eye);
  const z = dot(d, v.forward);
  if (z < NEAR) return null;
  return [v.cx + v.focal * dot(d, v.right) / z, v.cy - v.focal * dot(d, v.up) / z, z];
}

let drag = null;
canvas.addEventListener('pointerdown', (event) => {
  drag = { x: event.clientX, y: event.clientY };
  canvas.setPointerCapture(event.pointerId);
});
canvas.addEventListener('pointermove', (event) => {
  if (!drag) return;
  camera.yaw -= (event.clientX - drag.x) * 0.008;
  camera.pitch = Math.max(-0.2, Math.min(1.5, camera.pitch + (event.clientY - drag.y) * 0.008));
  drag = { x: event.clientX, y: event.clientY };
  cameraMoved = true;
  dirty = true;
});
canvas.addEventListener('pointerup', () => { drag = null; });
canvas.addEventListener('wheel', (event) => {
  event.preventDefault();
  camera.distance = Math.max(0.4, Math.min(40, camera.distance * Math.exp(event.deltaY * 0.001)));
  cameraMoved = true;
  dirty = true;
}, { passive: false });
canvas.addEventListener('dblclick', () => {
  Object.assign(camera, HOME_CAMERA);
  cameraMoved = false;
  dirty = true;
});

// Home: looking at the middle of everything there is to see (walls, cylinders, the rig),
// from far enough for all of it to fit.
// A long branch would shrink a small rig to a few pixels: only the part of each cylinder
// within CYLINDER_FIT_M of the rig counts.
const CYLINDER_FIT_M = 1.0;

function cylinderNear(c, centre) {
  const axis = sub(c.to, c.from);
  const length = Math.hypot(axis[0], axis[1], axis[2]) || 1;
  const along = dot(sub(centre, c.from), axis) / length;
  const at = (d) => {
    const k = Math.min(length, Math.max(0, d)) / length;
    return [0, 1, 2].map((i) => c.from[i] + k * axis[i]);
  };
  return [at(along - CYLINDER_FIT_M), at(along + CYLINDER_FIT_M)];
}

function fitCamera(chains) {
  linkRadius = linkRadiusFor(chains);
  const points = [];
  for (const wall of scene.walls) points.push(...wall.corners);
  const rig = chains.flat();
  if (rig.length > 0) {
    const centre = [0, 1, 2].map((k) => rig.reduce((sum, p) => sum + p[k], 0) / rig.length);
    for (const c of scene.cylinders) points.push(...cylinderNear(c, centre));
  } else {
    for (const c of scene.cylinders) points.push(c.from, c.to);
  }
  for (const chain of chains) points.push(...chain);
  if (points.length === 0) return;
  const low = [0, 1, 2].map((k) => Math.min(...points.map((p) => p[k])));
  const high = [0, 1, 2].map((k) => Math.max(...points.map((p) => p[k])));
  const radius = Math.hypot(high[0] - low[0], high[1] - low[1], high[2] - low[2]) / 2;
  HOME_CAMERA.target = [0, 1, 2].map((k) => (low[k] + high[k]) / 2);
  const reach = Math.max(...[0, 1].flatMap((k) => [Math.abs(low[k]), Math.abs(high[k])]));
  floorHalf = Math.max(2, Math.ceil(reach + 0.5));
  // A rig below z = 0 (the sloth hangs under its branch) gets its ground below it.
  floorZ = low[2] < -FLOOR_TOLERANCE ? low[2] - 0.3 : 0;
  // The view's half-angle is atan(0.5 / 0.9) (focal length 0.9 of the shorter side).
  HOME_CAMERA.distance = Math.max(1.0, 1.15 * radius / Math.sin(Math.atan(0.5 / 0.9)));
  if (!cameraMoved) Object.assign(camera, HOME_CAMERA);
}
let fitPending = true;

function resize() {
  const ratio = window.devicePixelRatio || 1;
  const width = Math.max(1, Math.round(canvas.clientWidth * ratio));
  const height = Math.max(1, Math.round(canvas.clientHeight * ratio));
  if (canvas.width !== width || canvas.height !== height) {
    canvas.width = width;
    canvas.height = height;
    dirty = true;
  }
}
window.addEventListener('resize', resize);

// ---------------------------------------------------------------------- scene --
let scene = { walls: [], cylinders: [], paint: [], solids: [], bodies: [] };
// The running job's plan (tool path and targets), whatever started the job; null before.
let plan = null;
// The cell's static objects' triangles in world coordinates, computed once per scene.
let solidTriangles = [];
let paintByWall = [];
let latest = null;
// Links and joints are drawn in proportion to the rig: the IRB 120's 0.27-0.3 m links get
// 4.5 cm, the sloth's 2-15 cm bones about 1.5 cm (set from the rig's first frame).
const MAX_LINK_RADIUS = 0.045;
const MIN_LINK_RADIUS = 0.008;
const LINK_RADIUS_PER_LENGTH = 0.17;
let linkRadius = MAX_LINK_RADIUS;

function linkRadiusFor(chains) {
  const lengths = [];
  for (const chain of chains) {
    for (let i = 1; i < chain.length; i++) {
      const d = sub(chain[i], chain[i - 1]);
      const length = Math.hypot(d[0], d[1], d[2]);
      if (length > 0.001) lengths.push(length);
    }
  }
  if (lengths.length === 0) return MAX_LINK_RADIUS;
  lengths.sort((a, b) => a - b);
  const median = lengths[Math.floor(lengths.length / 2)];
  return Math.min(MAX_LINK_RADIUS, Math.max(MIN_LINK_RADIUS, LINK_RADIUS_PER_LENGTH * median));
}
const BASE_RADIUS = 0.12;
const FLOOR_TOLERANCE = 0.01;
const CHAIN_COLOURS = ['#e8772e', '#2f7dd1', '#7a4fc4', '#1f9d74'];
// Drawing order before depth: walls facing the camera, then bodies, then walls seen from
// behind (outlines).
const LAYER_UNDER = 0;
const LAYER_BODY = 1;
const LAYER_OVER = 2;

function setScene(message) {
  scene = message.scene;
  health.sceneWalls = scene.walls.length;
  health.sceneCylinders = scene.cylinders.length;
  paintByWall = scene.walls.map(() => []);
  scene.solids = scene.solids || [];
  scene.bodies = scene.bodies || [];
  solidTriangles = scene.solids.map((s) => ({ name: s.name, triangles: posed(s.triangles, s.pose) }));
  health.sceneSolids = scene.solids.length;
  health.sceneBodies = scene.bodies.length;
  partSolids = message.parts || [];
  health.sceneParts = partSolids.length;
  plan = message.plan || null;
  health.planPoints = plan ? plan.tool_path.length : 0;
  health.planTargets = plan ? plan.targets.length : 0;
  health.paintQuads = 0;
  addPaint(scene.paint);
  document.getElementById('rig-name').textContent =
    message.rig + ' \u00b7 ' + message.rate_hz + ' Hz stream \u00b7 ' + message.frame_rate_hz + ' frames/s';
  buildJointTable(message.joints);
  fitPending = true;
  dirty = true;
}

function addPaint(quads) {
  for (const quad of quads) {
    if (paintByWall[quad.wall]) {
      paintByWall[quad.wall].push(quad.quad);
      health.paintQuads += 1;
    }
  }
}

// Lighter when facing the camera: a cheap cue for which way a surface turns.
function shade(rgb, normal, v) {
  const facing = Math.abs(dot(normalize(normal), v.forward));
  const k = 0.65 + 0.35 * facing;
  return 'rgb(' + rgb.map((c) => Math.round(c * k)).join(',') + ')';
}

function polygonPath(points) {
  ctx.moveTo(points[0][0], points[0][1]);
  for (let i = 1; i < points.length; i++) ctx.lineTo(points[i][0], points[i][1]);
  ctx.closePath();
}

function projectAll(v, points) {
  const out = [];
  for (const p of points) {
    const s = project(v, p);
    if (!s) return null;
    out.push(s);
  }
  return out;
}

function meanDepth(points) {
  return points.reduce((sum, p) => sum + p[2], 0) / points.length;
}

function wallDrawable(v, wall, index) {
  const outline = projectAll(v, wall.corners);
  if (!outline) return null;
  const holes = wall.openings.map((o) => projectAll(v, o)).filter((o) => o);
  const paint = paintByWall[index].map((q) => projectAll(v, q)).filter((q) => q);
  const normal = cross(sub(wall.corners[1], wall.corners[0]), sub(wall.corners[2], wall.corners[0]));
  // Seen from behind (a room's near wall, from outside): an outline, so the inside shows.
  const fromBehind = dot(normal, sub(v.eye, wall.corners[0])) < 0;
  const fill = shade([214, 209, 198], normal, v);
  return {
    // A wall is a plane: what stands on the camera's side of a wall facing the camera is
    // in front of all of it, whatever the centroids say; a wall seen from behind is an
    // outline over everything.
    layer: fromBehind ? LAYER_OVER : LAYER_UNDER,
    depth: meanDepth(outline),
    draw() {
      ctx.beginPath();
      polygonPath(outline);
      for (const hole of holes) polygonPath(hole);
      ctx.strokeStyle = '#8d877b';
      ctx.lineWidth = 1;
      if (fromBehind) {
        ctx.stroke();
        return;
      }
      ctx.fillStyle = fill;
      ctx.fill('evenodd');
      ctx.stroke();
      ctx.fillStyle = '#1f5fbf';
      ctx.beginPath();
      for (const quad of paint) polygonPath(quad);
      ctx.fill('nonzero');
    },
  };
}

function cylinderDrawable(v, cylinder) {
  const a = project(v, cylinder.from);
  const b = project(v, cylinder.to);
  if (!a || !b) return null;
  const ra = v.focal * cylinder.radius / a[2];
  const rb = v.focal * cylinder.radius / b[2];
  const dx = b[0] - a[0];
  const dy = b[1] - a[1];
  const n = Math.hypot(dx, dy) || 1;
  const px = -dy / n;
  const py = dx / n;
  const axis = sub(cylinder.to, cylinder.from);
  const side = cross(axis, v.forward);
  const fill = shade([124, 92, 58], cross(axis, side), v);
  return {
    depth: (a[2] + b[2]) / 2,
    draw() {
      ctx.fillStyle = fill;
      ctx.beginPath();
      ctx.moveTo(a[0] + px * ra, a[1] + py * ra);
      ctx.lineTo(b[0] + px * rb, b[1] + py * rb);
      ctx.lineTo(b[0] - px * rb, b[1] - py * rb);
      ctx.lineTo(a[0] - px * ra, a[1] - py * ra);
      ctx.closePath();
      ctx.fill();
      ctx.beginPath();
      ctx.arc(a[0], a[1], ra, 0, 2 * Math.PI);
      ctx.arc(b[0], b[1], rb, 0, 2 * Math.PI);
      ctx.fill();
    },
  };
}

// A point rotated by the unit quaternion q = [x, y, z, w] and moved by t.
function transform(p, q, t) {
  const [x, y, z, w] = q;
  const u = [x, y, z];
  const c = cross(u, p);
  const cc = cross(u, c);
  return [
    p[0] + 2 * (w * c[0] + cc[0]) + t[0],
    p[1] + 2 * (w * c[1] + cc[1]) + t[1],
    p[2] + 2 * (w * c[2] + cc[2]) + t[2],
  ];
}

// A solid's triangles (three points each, flat) at a pose, as [a, b, c] world triangles.
function posed(points, pose) {
  const out = [];
  for (let i = 0; i + 2 < points.length; i += 3) {
    out.push([0, 1, 2].map((k) => transform(points[i + k], pose.orientation, pose.position)));
  }
  return out;
}

// The colours of the cell's objects, the rig's collision bodies, and the closest pair
// within the margin (amber) or touching (red): RGB and opacity.
const OBJECT_COLOUR = [[140, 150, 160], 0.35];
const BODY_COLOUR = [[240, 150, 50], 0.3];
const NEAR_COLOUR = [[240, 190, 25], 0.85];
const HIT_COLOUR = [[215, 25, 25], 0.9];

// Each triangle facing the camera, as its own drawable (depth sorts it among the rest).
function solidDrawables(v, triangles, colour, out) {
  const [rgb, alpha] = colour;
  for (const t of triangles) {
    const normal = cross(sub(t[1], t[0]), sub(t[2], t[0]));
    if (dot(normal, sub(v.eye, t[0])) <= 0) continue;
    const points = projectAll(v, t);
    if (!points) continue;
    const fill = shade(rgb, normal, v);
    out.push({
      depth: meanDepth(points),
      draw() {
        ctx.globalAlpha = alpha;
        ctx.fillStyle = fill;
        ctx.beginPath();
        polygonPath(points);
        ctx.fill();
        ctx.globalAlpha = 1;
      },
    });
  }
}

// The cell's parts' solids (each in its own frame; a frame's program.parts poses them),
// coloured by the twin's judgement of each: at rest or carried, placed, dropped.
let partSolids = [];
const PART_COLOURS = {
  never_picked: [[120, 120, 200], 0.8],
  carried: [[40, 120, 240], 0.9],
  placed: [[40, 170, 70], 0.9],
  dropped: [[215, 25, 25], 0.9],
};

function partDrawables(v, frame, out) {
  const program = frame && frame.program;
  if (!program) return;
  const judged = (program.judgement && program.judgement.per_part) || [];
  partSolids.forEach((part, i) => {
    const pose = program.parts[i];
    if (!pose) return;
    const state = judged[i] ? judged[i].state : 'never_picked';
    solidDrawables(v, posed(part.triangles, pose), PART_COLOURS[state] || PART_COLOURS.never_picked, out);
  });
}

// The program's step and the twin's tally of the parts, in words.
function programText(program) {
  if (!program) return ['', ''];
  const step = program.step ? program.step.text : '';
  health.programStep = step;
  const j = program.judgement;
  const parts = j
    ? 'parts: ' + j.placed + ' of ' + j.parts + ' placed, ' + j.carried + ' carried, ' + j.dropped +
      ' dropped, ' + j.never_picked + ' not picked yet; ' + j.collisions + ' carried with collisions, ' +
      j.struck + ' struck at rest (worst placed ' + j.worst_position_error_mm.toFixed(3) + ' mm, ' +
      j.worst_orientation_error_deg.toFixed(3) + ' deg)'
    : '';
  return [step, parts];
}

// The closest pair's names when it is marked, and its colour.
function closestMark(frame) {
  const closest = frame && frame.closest;
  if (!closest) return null;
  return { names: [closest.a, closest.b], colour: closest.distance_m <= 0 ? HIT_COLOUR : NEAR_COLOUR };
}

function cellDrawables(v, frame, out) {
  const mark = closestMark(frame);
  const colourOf = (name, normal) => (mark && mark.names.includes(name) ? mark.colour : normal);
  for (const s of solidTriangles) solidDrawables(v, s.triangles, colourOf(s.name, OBJECT_COLOUR), out);
  partDrawables(v, frame, out);
  if (!frame || !frame.bodies) return;
  scene.bodies.forEach((body, i) => {
    const pose = frame.bodies[i];
    if (!pose) return;
    const triangles = posed(body.solid.triangles, pose);
    solidDrawables(v, triangles, colourOf(body.solid.name, BODY_COLOUR), out);
  });
}

// A disc on the floor around the chain's first point: the rig's base.
function baseDrawable(v, origin) {
  const rim = [];
  for (let k = 0; k < 20; k++) {
    const angle = (k / 20) * 2 * Math.PI;
    rim.push([origin[0] + BASE_RADIUS * Math.cos(angle), origin[1] + BASE_RADIUS * Math.sin(angle), origin[2]]);
  }
  const points = projectAll(v, rim);
  if (!points) return null;
  return {
    // Flat on the floor: drawn before the links standing on it, in order with the walls.
    depth: meanDepth(points) + BASE_RADIUS,
    draw() {
      ctx.fillStyle = '#4b5563';
      ctx.beginPath();
      polygonPath(points);
      ctx.fill();
    },
  };
}

function chainDrawables(v, chain, colour, out) {
  const points = chain.map((p) => project(v, p));
  for (let i = 0; i + 1 < points.length; i++) {
    const a = points[i];
    const b = points[i + 1];
    if (!a || !b) continue;
    out.push({
      depth: (a[2] + b[2]) / 2,
      draw() {
        ctx.strokeStyle = colour;
        ctx.lineCap = 'round';
        ctx.lineWidth = Math.max(2, 2 * v.focal * linkRadius / ((a[2] + b[2]) / 2));
        ctx.beginPath();
        ctx.moveTo(a[0], a[1]);
        ctx.lineTo(b[0], b[1]);
        ctx.stroke();
      },
    });
  }
  points.forEach((p, i) => {
    if (!p) return;
    const tool = i === points.length - 1;
    out.push({
      depth: p[2] - 0.001,
      draw() {
        ctx.fillStyle = tool ? '#111827' : '#374151';
        ctx.beginPath();
        ctx.arc(p[0], p[1], Math.max(2, v.focal * (tool ? 0.6 : 1) * 1.22 * linkRadius / p[2]), 0, 2 * Math.PI);
        ctx.fill();
      },
    });
  });
}

// The plan's tool path as a thin line and its targets as rings, over the floor and under
// everything else: a guide to where the tool will go, not a thing in the cell. Solid, not
// dashed, and thinned on screen: both cheaper for software rendering.
const PLAN_COLOUR = '#16a34a';
const TARGET_RADIUS_PX = 4;
// Points of the path closer than this on screen to the last one drawn are skipped: a
// 2 000-point path stroked whole cost the room view frames under software rendering.
const PLAN_STEP_PX = 3;
function drawPlan(v) {
  if (!plan) return;
  ctx.strokeStyle = PLAN_COLOUR;
  ctx.lineWidth = 1.5;
  ctx.beginPath();
  let last = null;
  const final = plan.tool_path.length - 1;
  plan.tool_path.forEach((point, i) => {
    const p = project(v, point);
    if (!p) {
      last = null;
      return;
    }
    if (!last) {
      ctx.moveTo(p[0], p[1]);
      last = p;
    } else if (i === final || Math.abs(p[0] - last[0]) + Math.abs(p[1] - last[1]) >= PLAN_STEP_PX) {
      ctx.lineTo(p[0], p[1]);
      last = p;
    }
  });
  ctx.stroke();
  for (const target of plan.targets) {
    const p = project(v, target.at);
    if (!p) continue;
    ctx.beginPath();
    ctx.arc(p[0], p[1], TARGET_RADIUS_PX, 0, 2 * Math.PI);
    ctx.stroke();
  }
}

// The floor's grid: 0.2 m squares, 0.5 m in scenes wider than 8 m, reaching past the scene.
let floorHalf = 2;
let floorZ = 0;
function drawFloor(v) {
  ctx.strokeStyle = '#cfd5dd';
  ctx.lineWidth = 1;
  ctx.beginPath();
  const step = floorHalf > 4 ? 0.5 : 0.2;
  const lines = Math.round(floorHalf / step);
  for (let k = -lines; k <= lines; k++) {
    const x = k * step;
    const h = floorHalf;
    for (const [p, q] of [[[x, -h, floorZ], [x, h, floorZ]], [[-h, x, floorZ], [h, x, floorZ]]]) {
      const a = project(v, p);
      const b = project(v, q);
      if (!a || !b) continue;
      ctx.moveTo(a[0], a[1]);
      ctx.lineTo(b[0], b[1]);
    }
  }
  ctx.stroke();
}

function draw() {
  resize();
  const v = view();
  ctx.fillStyle = '#f7f8fa';
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  drawFloor(v);
  drawPlan(v);
  const drawables = [];
  scene.walls.forEach((wall, i) => drawables.push(wallDrawable(v, wall, i)));
  scene.cylinders.forEach((c) => drawables.push(cylinderDrawable(v, c)));
  cellDrawables(v, latest, drawables);
  if (latest) {
    latest.chains.forEach((chain, i) => {
      if (chain.length === 0) return;
      // The rig's first chain stands on a base plate when it starts on the floor (the arm);
      // a limb, a brush or a contact line does not.
      if (i === 0 && Math.abs(chain[0][2]) < FLOOR_TOLERANCE) drawables.push(baseDrawable(v, chain[0]));
      chainDrawables(v, chain, CHAIN_COLOURS[i % CHAIN_COLOURS.length], drawables);
    });
  }
  // Painter's algorithm: by layer, then farthest first.
  drawables
    .filter((d) => d)
    .sort((a, b) => (a.layer ?? LAYER_BODY) - (b.layer ?? LAYER_BODY) || b.depth - a.depth)
    .forEach((d) => d.draw());
  health.framesDrawn += 1;
  if (health.firstFrameMs === null && latest) {
    health.firstFrameMs = performance.now();
    document.getElementById('first-frame').textContent = health.firstFrameMs.toFixed(0) + ' ms after load';
  }
}

function animate() {
  if (dirty) {
    dirty = false;
    draw();
  }
  requestAnimationFrame(animate);
}

// -------------------------------------------------------------------- status --
function format(value, digits) {
  return typeof value === 'number' && isFinite(value) ? value.toFixed(digits) : '-';
}

let jointUnits = [];
function buildJointTable(joints) {
  jointUnits = joints.map((j) => j.unit);
  const body = document.querySelector('#joints tbody');
  body.textContent = '';
  joints.forEach((joint, i) => {
    const row = body.insertRow();
    row.insertCell().textContent = joint.name;
    row.insertCell().id = 'joint-actual-' + i;
    row.insertCell().id = 'joint-commanded-' + i;
    row.insertCell().textContent = joint.unit;
    row.cells[0].style.textAlign = 'left';
  });
}

const LINK_ROWS = [
  ['status', 'controller', (l) => l.status],
  ['rate', 'rate (set / measured) Hz', (l) => format(l.rate_hz, 0) + ' / ' + format(l.cycles_per_s, 0)],
  ['cycles', 'cycles', (l) => String(l.cycles)],
  ['jitter', 'jitter (last / max 1 s) \u00b5s', (l) => format(l.jitter_us, 0) + ' / ' + format(l.jitter_max_us, 0)],
  ['latency', 'latency (last / max 1 s) \u00b5s', (l) => format(l.latency_us, 0) + ' / ' + format(l.latency_max_us, 0)],
  ['tracking', 'tracking error deg', (l) => format(l.tracking_error_deg, 3)],
  ['frames', 'frames sent / received', (l) => l.frames_sent + ' / ' + l.frames_received],
  ['errors', 'crc / dup / gaps / reconnects', (l) => [l.crc_errors, l.duplicates, l.gaps, l.reconnects].join(' / ')],
  ['timeouts', 'feedback timeouts', (l) => String(l.feedback_timeouts)],
];
(function buildLinkTable() {
  const body = document.querySelector('#link tbody');
  for (const [key, label] of LINK_ROWS) {
    const row = body.insertRow();
    row.insertCell().textContent = label;
    row.insertCell().id = 'link-' + key;
    row.cells[0].style.textAlign = 'left';
    row.cells[0].style.color = '#5b6472';
  }
})();

function showStatus(frame) {
  frame.actual.forEach((value, i) => {
    const digits = jointUnits[i] === 'm' ? 4 : 2;
    const actual = document.getElementById('joint-actual-' + i);
    if (actual) actual.textContent = format(value, digits);
    const commanded = document.getElementById('joint-commanded-' + i);
    if (commanded) commanded.textContent = format(frame.commanded[i], digits);
  });
  for (const [key, , text] of LINK_ROWS) {
    document.getElementById('link-' + key).textContent = text(frame.link);
  }
  const job = frame.job;
  // A latched fault outlives the last streamed cycle's status (which predates it): it
  // shows until a reset clears it, never "ok" beside an e-stop.
  const controller = document.getElementById('link-status');
  if (job.controller) controller.textContent = 'fault: ' + job.controller + ' (reset to clear)';
  controller.classList.toggle('fault', Boolean(job.controller));
  document.getElementById('job-state').textContent = job.state;
  document.getElementById('job-name').textContent = job.name ? '(' + job.name + ' #' + job.id + ')' : '';
  document.getElementById('job-progress').value = job.progress;
  document.getElementById('job-percent').textContent = (100 * job.progress).toFixed(1) + ' %';
  document.getElementById('job-last').textContent = job.last ? 'last job: ' + job.last : '';
  const [step, parts] = programText(frame.program);
  document.getElementById('program-step').textContent = step ? 'step: ' + step : '';
  document.getElementById('program-parts').textContent = parts;
  // The cell's closest pair, while it is within the margin (or touching).
  const closest = frame.closest;
  document.getElementById('closest').textContent = closest
    ? closest.a + ' \u2013 ' + closest.b + ': ' + closest.distance_m.toFixed(4) + ' m (' + closest.status + ')'
    : '';
  // A failed log is said as soon as the writer meets it, and stays until the next job.
  document.getElementById('job-log-error').textContent = job.log_error ? 'log failed: ' + job.log_error : '';
}

// Rates over the last second.
let lastRateAt = performance.now();
let lastFrames = 0;
let lastMessages = 0;
setInterval(() => {
  const now = performance.now();
  const seconds = (now - lastRateAt) / 1000;
  health.fps = (health.framesDrawn - lastFrames) / seconds;
  health.wsRate = (health.wsMessages - lastMessages) / seconds;
  lastRateAt = now;
  lastFrames = health.framesDrawn;
  lastMessages = health.wsMessages;
  document.getElementById('fps').textContent = health.fps.toFixed(1);
  document.getElementById('ws-rate').textContent = health.wsRate.toFixed(1);
}, 1000);

// ------------------------------------------------------------------ WebSocket --
function setConnection(state, text) {
  const badge = document.getElementById('connection');
  badge.className = 'badge ' + state;
  badge.textContent = text;
}

// A token that is a valid subprotocol name travels as one (kept out of URLs and logs);
// any other goes in the query string.
const PROTOCOL_TOKEN = /^[!#$%&'*+\-.^_`|~0-9A-Za-z]+$/;

// The cell on show: its routes live under /api/cells/<name>/; until the list of cells
// arrives (and for the first cell) the routes without a name, which are the first cell's.
let cellPrefix = '/api';

let socket = null;
function connect() {
  const scheme = location.protocol === 'https:' ? 'wss://' : 'ws://';
  let url = scheme + location.host + cellPrefix + '/live';
  const protocols = ['rigbridge.live'];
  if (token && PROTOCOL_TOKEN.test(token)) {
    protocols.push('rigbridge.token.' + token);
  } else if (token) {
    url += '?token=' + encodeURIComponent(token);
  }
  let opened = false;
  const mine = new WebSocket(url, protocols);
  socket = mine;
  mine.addEventListener('open', () => {
    opened = true;
    setConnection('live', 'live');
  });
  mine.addEventListener('message', (event) => {
    if (socket !== mine) return;
    health.wsMessages += 1;
    const message = JSON.parse(event.data);
    if (message.type === 'scene') {
      setScene(message);
    } else if (message.type === 'frame') {
      latest = message;
      if (fitPending) {
        fitPending = false;
        fitCamera(message.chains);
      }
      addPaint(message.paint);
      showStatus(message);
      dirty = true;
    }
  });
  mine.addEventListener('close', () => {
    // A socket closed because another cell was chosen: its successor is already open.
    if (socket !== mine) return;
    if (!opened) {
      // Refused before opening: most likely a missing or wrong token.
      askForToken('refused: token?');
      return;
    }
    setConnection('down', 'disconnected, retrying');
    setTimeout(connect, 1000);
  });
}

// ----------------------------------------------------------------------- cells --
// One daemon may run several rigs (cells); the selector shows when there is more than one.
const cellSelect = document.getElementById('cell');

async function loadCells() {
  try {
    const response = await fetch('/api/cells', { headers: authHeaders() });
    if (!response.ok) return;
    const body = await response.json();
    const chosen = cellSelect.value;
    cellSelect.textContent = '';
    for (const cell of body.cells) {
      const option = document.createElement('option');
      option.value = cell.name;
      option.textContent = cell.name + ' (' + cell.dof + ' axes)';
      cellSelect.appendChild(option);
    }
    if (chosen) cellSelect.value = chosen;
    cellSelect.hidden = body.cells.length < 2;
  } catch (error) {
    recordError('cannot list the cells: ' + error);
  }
}

function showCell(name) {
  cellPrefix = cellSelect.selectedIndex === 0 ? '/api' : '/api/cells/' + encodeURIComponent(name);
  latest = null;
  fitPending = true;
  // Another rig in another scene: the camera a person set for the last one means nothing here.
  cameraMoved = false;
  const old = socket;
  connect();
  if (old) old.close();
}
cellSelect.addEventListener('change', () => showCell(cellSelect.value));

// -------------------------------------------------------------------- controls --
async function control(action) {
  const path = cellPrefix + action;
  const result = document.getElementById('control-result');
  result.textContent = path + ' ...';
  try {
    // The API takes control requests only as JSON (a cross-site form cannot send that).
    const headers = Object.assign({ 'Content-Type': 'application/json' }, authHeaders());
    const response = await fetch(path, { method: 'POST', headers });
    const body = await response.json().catch(() => ({}));
    if (response.status === 401) askForToken('token needed');
    result.textContent = path + ': ' + response.status + (body.error ? ' ' + body.error : '');
  } catch (error) {
    result.textContent = path + ': ' + error;
  }
}
// A job pasted as JSON (`{"job": {...}}` or the job alone) or as TOML (a `[job]` table or
// its keys): JSON goes as it is, TOML as text the server parses and validates like a job
// file. The answer (the job's number, or the refusal naming key and value) shows below.
async function startPasted() {
  const text = document.getElementById('paste').value;
  const result = document.getElementById('paste-result');
  let body;
  try {
    const parsed = JSON.parse(text);
    body = parsed && typeof parsed === 'object' && ('job' in parsed || 'toml' in parsed) ? parsed : { job: parsed };
  } catch (_) {
    body = { toml: text };
  }
  result.className = '';
  result.textContent = 'starting ...';
  try {
    const headers = Object.assign({ 'Content-Type': 'application/json' }, authHeaders());
    const response = await fetch(cellPrefix + '/jobs', { method: 'POST', headers, body: JSON.stringify(body) });
    const answer = await response.json().catch(() => ({}));
    if (response.status === 401) askForToken('token needed');
    if (response.ok) {
      result.textContent = 'started job ' + answer.id + ' (' + answer.job + ')';
    } else {
      result.className = 'fault';
      result.textContent = response.status + ': ' + (answer.error || response.statusText);
    }
  } catch (error) {
    result.className = 'fault';
    result.textContent = String(error);
  }
}
document.getElementById('paste-start').addEventListener('click', startPasted);

const CONTROLS = { start: '/jobs', pause: '/pause', resume: '/resume', stop: '/stop', estop: '/estop', reset: '/reset' };
for (const [id, path] of Object.entries(CONTROLS)) {
  document.getElementById(id).addEventListener('click', () => control(path));
}

// ---------------------------------------------------------------- speed and jog --
// The override slider posts on release; a jog button posts its jog on press, a keep-alive
// every KEEP_ALIVE_MS while held (the bridge stops the arm 200 ms after the last one) and
// a release when let go, lost or left.
const KEEP_ALIVE_MS = 50;
async function post(action, body) {
  const headers = Object.assign({ 'Content-Type': 'application/json' }, authHeaders());
  const response = await fetch(cellPrefix + action, { method: 'POST', headers, body: JSON.stringify(body) });
  if (response.status === 401) askForToken('token needed');
  if (!response.ok) {
    const answer = await response.json().catch(() => ({}));
    document.getElementById('control-result').textContent =
      cellPrefix + action + ': ' + response.status + (answer.error ? ' ' + answer.error : '');
  }
  return response.ok;
}
const speedInput = document.getElementById('speed');
speedInput.addEventListener('input', () => {
  document.getElementById('speed-value').textContent = speedInput.value + ' %';
});
speedInput.addEventListener('change', () => post('/speed', { percent: Number(speedInput.value) }));

let jogTimer = null;
function jogStart(body) {
  jogStop(false);
  post('/jog', body);
  jogTimer = setInterval(() => post('/jog', { keep_alive: true }), KEEP_ALIVE_MS);
}
function jogStop(release) {
  if (jogTimer === null) return;
  clearInterval(jogTimer);
  jogTimer = null;
  if (release) post('/jog', { release: true });
}
const jogFrame = document.getElementById('jog-frame');
const AXES = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
function jogBody(index, sign) {
  if (jogFrame.value === 'joint') return { axis: index + 1, direction: sign };
  return { frame: jogFrame.value, direction: AXES[index].map((c) => c * sign) };
}
function jogButtons() {
  const box = document.getElementById('jog-buttons');
  box.textContent = '';
  const count = jogFrame.value === 'joint' ? 6 : 3;
  for (let index = 0; index < count; index++) {
    for (const sign of [-1, 1]) {
      const button = document.createElement('button');
      button.type = 'button';
      const name = jogFrame.value === 'joint' ? 'J' + (index + 1) : 'XYZ'[index];
      button.textContent = name + (sign > 0 ? '+' : '-');
      button.addEventListener('pointerdown', () => jogStart(jogBody(index, sign)));
      for (const end of ['pointerup', 'pointerleave', 'pointercancel']) {
        button.addEventListener(end, () => jogStop(true));
      }
      box.appendChild(button);
    }
  }
}
jogFrame.addEventListener('change', jogButtons);
jogButtons();
const JOG_KEYS = { '1': 0, '2': 1, '3': 2, '4': 3, '5': 4, '6': 5, x: 0, y: 1, z: 2 };
window.addEventListener('keydown', (event) => {
  // Typing a job in the paste box (or a token) must never jog the arm.
  const typing = event.target instanceof HTMLInputElement || event.target instanceof HTMLTextAreaElement;
  if (event.repeat || typing) return;
  const index = JOG_KEYS[event.key.toLowerCase()] ?? JOG_KEYS[event.code.replace('Digit', '')];
  if (index === undefined) return;
  jogStart(jogBody(index, event.shiftKey ? -1 : 1));
});
window.addEventListener('keyup', () => jogStop(true));
window.addEventListener('blur', () => jogStop(true));

resize();
connect();
loadCells();
requestAnimationFrame(animate);
