// The floor-plan page of drvs_gateway: the floor seen from above, live (docs/gateway.md, "The
// floor-plan page"). Plain JavaScript and SVG, no library. The token stays in this tab's
// sessionStorage and goes in a header to POST /v1/tickets; the event stream is opened with the
// one-use ticket that returns, never with the token in a URL.
'use strict';

const SVG = 'http://www.w3.org/2000/svg';
const TOKEN_KEY = 'drvs-token';
const MARGIN = 0.5; // metres around what is drawn
const state = { registry: [], objects: [], robots: new Map(), paths: new Map(), bounds: null };
let source = null;
let retryTimer = null;
let drawPending = false;

const $ = (id) => document.getElementById(id);

function showError(text) {
  const box = $('error');
  box.textContent = text;
  box.hidden = !text;
}

function setConnection(text, live) {
  const label = $('connection');
  label.textContent = text;
  label.classList.toggle('live', !!live);
}

function askForToken(message) {
  if (source) { source.close(); source = null; }
  $('login').hidden = false;
  $('view').hidden = true;
  setConnection('not connected');
  showError(message || '');
  $('token').focus();
}

async function connect() {
  clearTimeout(retryTimer);
  const token = sessionStorage.getItem(TOKEN_KEY);
  const headers = token ? { Authorization: 'Bearer ' + token } : {};
  let response;
  try {
    response = await fetch('/v1/tickets', { method: 'POST', headers, cache: 'no-store' });
  } catch (error) {
    showError('Cannot reach the gateway (' + error.message + '); trying again.');
    setConnection('reconnecting');
    retryTimer = setTimeout(connect, 2000);
    return;
  }
  if (response.status === 401 || response.status === 403) {
    const body = await response.json().catch(() => ({}));
    if (token) sessionStorage.removeItem(TOKEN_KEY);
    const why = body.message ? ': ' + body.message : '';
    // No token yet: the form alone asks for one; a refused token: say why, clearly.
    askForToken(
      !token ? ''
        : response.status === 401 ? 'The token was refused (HTTP 401, unknown token' + why + ').'
          : 'This token may not read the floor plan (HTTP 403' + why + ').');
    return;
  }
  if (!response.ok) {
    const body = await response.json().catch(() => ({}));
    showError('The gateway answered HTTP ' + response.status + (body.message ? ': ' + body.message : '') + '; trying again.');
    retryTimer = setTimeout(connect, 2000);
    return;
  }
  const ticket = await response.json();
  $('login').hidden = true;
  $('view').hidden = false;
  showError('');
  listen(ticket.live);
}

function listen(url) {
  if (source) source.close();
  source = new EventSource(url);
  source.onopen = () => setConnection('live', true);
  source.onerror = () => {
    // A ticket is good once: a new one for the next stream.
    source.close();
    source = null;
    setConnection('reconnecting');
    retryTimer = setTimeout(connect, 1000);
  };
  source.addEventListener('registry', (event) => {
    state.registry = JSON.parse(event.data).vision_systems || [];
    redraw();
  });
  source.addEventListener('objects', (event) => {
    state.objects = JSON.parse(event.data).objects || [];
    redraw();
  });
  source.addEventListener('robot', (event) => {
    const robot = JSON.parse(event.data);
    state.robots.set(robot.name, robot);
    redraw();
  });
  source.addEventListener('path', (event) => {
    const path = JSON.parse(event.data);
    state.paths.set(path.name, path.points || []);
    redraw();
  });
}

function redraw() {
  if (drawPending) return;
  drawPending = true;
  requestAnimationFrame(() => { drawPending = false; draw(); });
}

function el(name, attributes, parent, text) {
  const node = document.createElementNS(SVG, name);
  for (const [key, value] of Object.entries(attributes)) node.setAttribute(key, value);
  if (text !== undefined) node.textContent = text;
  if (parent) parent.appendChild(node);
  return node;
}

const finite = (point) => Array.isArray(point) && point.length >= 2 && Number.isFinite(point[0]) && Number.isFinite(point[1]);
// Map x right, map y up: the SVG's y is -y.
const pointsAttr = (points) => points.filter(finite).map(([x, y]) => x.toFixed(3) + ',' + (-y).toFixed(3)).join(' ');

function shortName(name) {
  // '/vs1/detect_object_boundary' -> 'vs1'
  const parts = String(name).split('/').filter(Boolean);
  return parts.length > 1 ? parts.slice(0, -1).join('/') : parts.join('/');
}

function grow(bounds, points) {
  for (const point of points) {
    if (!finite(point)) continue;
    bounds[0] = Math.min(bounds[0], point[0]); bounds[1] = Math.min(bounds[1], point[1]);
    bounds[2] = Math.max(bounds[2], point[0]); bounds[3] = Math.max(bounds[3], point[1]);
  }
}

function updateBounds() {
  const bounds = [Infinity, Infinity, -Infinity, -Infinity];
  for (const entry of state.registry) grow(bounds, entry.field_of_view || []);
  for (const robot of state.robots.values()) grow(bounds, [robot.position, robot.goal]);
  for (const points of state.paths.values()) grow(bounds, points);
  for (const found of state.objects) grow(bounds, found.boundary || []);
  if (!Number.isFinite(bounds[0])) return;
  // Only ever grows: the picture does not jump about as a robot moves.
  const old = state.bounds;
  state.bounds = old ? [Math.min(old[0], bounds[0] - MARGIN), Math.min(old[1], bounds[1] - MARGIN),
    Math.max(old[2], bounds[2] + MARGIN), Math.max(old[3], bounds[3] + MARGIN)]
    : [bounds[0] - MARGIN, bounds[1] - MARGIN, bounds[2] + MARGIN, bounds[3] + MARGIN];
}

function clear(id) {
  const group = $(id);
  while (group.firstChild) group.removeChild(group.firstChild);
  return group;
}

function draw() {
  updateBounds();
  const svg = $('floor');
  if (state.bounds) {
    const [minX, minY, maxX, maxY] = state.bounds;
    svg.setAttribute('viewBox', [minX, -maxY, maxX - minX, maxY - minY].map((v) => v.toFixed(3)).join(' '));
    const grid = clear('grid');
    for (let x = Math.ceil(minX); x <= maxX; x++) el('line', { class: 'grid', x1: x, x2: x, y1: -maxY, y2: -minY }, grid);
    for (let y = Math.ceil(minY); y <= maxY; y++) el('line', { class: 'grid', x1: minX, x2: maxX, y1: -y, y2: -y }, grid);
  }
  const fovs = clear('fovs');
  const labels = clear('labels');
  for (const entry of state.registry) {
    const points = (entry.field_of_view || []).filter(finite);
    if (points.length < 3) continue;
    el('polygon', { class: 'fov', 'data-name': entry.name, points: pointsAttr(points) }, fovs);
    const cx = points.reduce((sum, p) => sum + p[0], 0) / points.length;
    const top = Math.max(...points.map((p) => p[1]));
    el('text', { class: 'fov-label', x: cx.toFixed(3), y: (-top + 0.3).toFixed(3), 'text-anchor': 'middle' }, labels,
      shortName(entry.name));
  }
  const paths = clear('paths');
  for (const [name, points] of state.paths) {
    if (points.length > 1) el('polyline', { class: 'path', 'data-name': name, points: pointsAttr(points) }, paths);
  }
  const objects = clear('objects');
  for (const found of state.objects) {
    const outline = (found.boundary || []).filter(finite);
    if (outline.length < 3) continue;
    el('polygon', { class: 'object' + (found.stationary ? ' stationary' : ''), 'data-track': found.track_id,
      points: pointsAttr(outline) }, objects);
    const cx = outline.reduce((sum, p) => sum + p[0], 0) / outline.length;
    const cy = outline.reduce((sum, p) => sum + p[1], 0) / outline.length;
    const [vx, vy] = found.velocity || [0, 0];
    if (!found.stationary && Number.isFinite(vx) && Number.isFinite(vy) && Math.hypot(vx, vy) > 0.02) {
      el('line', { class: 'velocity', x1: cx, y1: -cy, x2: cx + vx, y2: -(cy + vy) }, objects);
    }
    const speed = Number.isFinite(vx) && Number.isFinite(vy) ? ' ' + Math.hypot(vx, vy).toFixed(2) + ' m/s' : '';
    const name = found.track_id ? '#' + found.track_id : (found.label || '');
    el('text', { class: 'object-label', x: cx.toFixed(3), y: (-cy - 0.25).toFixed(3), 'text-anchor': 'middle' }, labels,
      name + (found.track_id ? speed : ''));
  }
  const robots = clear('robots');
  for (const [name, robot] of state.robots) {
    if (finite(robot.goal)) {
      el('circle', { class: 'goal', cx: robot.goal[0], cy: -robot.goal[1], r: 0.15 }, robots);
    }
    if (!finite(robot.position)) continue;
    const [x, y] = robot.position;
    const marker = el('g', { class: 'robot', 'data-name': name, transform: `translate(${x.toFixed(3)} ${(-y).toFixed(3)})` }, robots);
    el('circle', { r: 0.17 }, marker);
    if (Number.isFinite(robot.heading)) {
      el('line', { x1: 0, y1: 0, x2: (0.17 * Math.cos(robot.heading)).toFixed(3), y2: (-0.17 * Math.sin(robot.heading)).toFixed(3) }, marker);
    }
    el('text', { class: 'robot-label', x: x.toFixed(3), y: (-y + 0.4).toFixed(3), 'text-anchor': 'middle' }, labels, name);
  }
  drawTables();
  $('updated').textContent = 'updated ' + new Date().toLocaleTimeString();
}

function row(body, cells) {
  const tr = document.createElement('tr');
  for (const cell of cells) {
    const td = document.createElement('td');
    td.textContent = cell;
    tr.appendChild(td);
  }
  body.appendChild(tr);
}

const metres = (value) => (Number.isFinite(value) ? value.toFixed(2) + ' m' : '—');

function drawTables() {
  const robotBody = $('robot-table').tBodies[0];
  robotBody.replaceChildren();
  for (const [name, robot] of state.robots) {
    const where = finite(robot.position) ? robot.position.map((v) => v.toFixed(2)).join(', ') : '—';
    row(robotBody, [name, robot.state + (robot.reason ? ' (' + robot.reason + ')' : ''), where, metres(robot.distance_to_goal)]);
  }
  const objectBody = $('object-table').tBodies[0];
  objectBody.replaceChildren();
  for (const found of state.objects) {
    const [vx, vy] = found.velocity || [];
    const velocity = Number.isFinite(vx) && Number.isFinite(vy) ? `${vx.toFixed(2)}, ${vy.toFixed(2)} m/s` : '—';
    row(objectBody, [found.track_id || '—', found.label || '', found.algorithm || '',
      found.stationary ? 'stationary' : velocity, (found.seen_by || []).map(shortName).join(', ')]);
  }
}

document.addEventListener('DOMContentLoaded', () => {
  $('login').addEventListener('submit', (event) => {
    event.preventDefault();
    sessionStorage.setItem(TOKEN_KEY, $('token').value.trim());
    $('token').value = '';
    connect();
  });
  $('logout').addEventListener('click', () => {
    sessionStorage.removeItem(TOKEN_KEY);
    askForToken('');
  });
  connect();
});
