// omnispectral viewer: Photo Sphere Viewer on server-rendered equirectangular tiles, spectra on click.
// Directions: PSV yaw 0 is the panorama's centre column (longitude 0) and grows to the right, as longitude
// does in omnispectral's equirectangular frame; pitch is latitude.
import { Viewer } from '@photo-sphere-viewer/core';
import { EquirectangularTilesAdapter } from '@photo-sphere-viewer/equirectangular-tiles-adapter';

const $ = (id) => document.getElementById(id);
const DEG = 180 / Math.PI;
const COLORS = ['#ffb000', '#38c8ff'];
const info = await (await fetch('api/info')).json();
const params = new URLSearchParams(location.search);
const state = { t: 0, mode: 'colour', band: 0, ev: 0, points: [null, null] };
const omni = { info, state, probes: [null, null], day: null, loads: 0, errors: [] };
window.omni = omni;

function query() {
  return `t=${state.t}&mode=${state.mode}&band=${state.band}&ev=${state.ev}`;
}

function panorama() {
  const q = query();
  return {
    baseUrl: `api/base.png?${q}`,
    levels: info.levels,
    tileUrl: (col, row, level) => `api/tile/${level}/${col}/${row}.png?${q}`,
  };
}

const viewer = new Viewer({
  container: $('viewer'),
  adapter: EquirectangularTilesAdapter.withConfig({ resolution: info.resolution, baseBlur: false }),
  panorama: panorama(),
  caption: info.name,
  defaultYaw: Number(params.get('lon') ?? 0) / DEG,
  defaultPitch: Number(params.get('lat') ?? 0) / DEG,
  defaultZoomLvl: Number(params.get('zoom') ?? 30),
  navbar: ['zoom', 'move', 'caption', 'fullscreen'],
  loadingTxt: 'loading…',
});
omni.viewer = viewer;
viewer.addEventListener('panorama-loaded', () => { omni.loads += 1; });
viewer.addEventListener('panorama-error', (e) => { omni.errors.push(String(e.error)); });

function reload() {
  $('status').textContent = '';
  viewer.setPanorama(panorama(), {
    transition: false, showLoader: false, position: viewer.getPosition(), zoom: viewer.getZoomLevel(),
  });
}

// ------------------------------------------------------------------ display controls
$('title').textContent = `${info.name}  (${info.width}×${info.height})`;
info.bands.forEach((name, i) => { $('band').add(new Option(name, String(i))); });
$('legend').innerHTML = `<span style="left:0">0</span><span style="right:0">${info.uncertainty_max}</span>`;
if (!info.has_quality) $('mode-registration').remove();

$('mode').addEventListener('change', () => {
  state.mode = $('mode').value;
  $('band-row').hidden = state.mode !== 'band';
  $('ev-row').hidden = state.mode === 'uncertainty' || state.mode === 'registration';
  $('legend').hidden = state.mode !== 'uncertainty';
  reload();
});
$('band').addEventListener('change', () => { state.band = Number($('band').value); reload(); });

function setEv(ev) {
  state.ev = ev;
  $('ev').value = String(ev);
  $('ev-value').textContent = `${ev > 0 ? '+' : ''}${ev} EV`;
}
$('ev').addEventListener('input', () => { $('ev-value').textContent = `${$('ev').value} EV`; });
$('ev').addEventListener('change', () => { setEv(Number($('ev').value)); reload(); });
$('auto').addEventListener('click', async () => {
  const pos = viewer.getPosition();
  const fov = viewer.state.vFov ?? 60;
  const q = `lon=${wrapLon(pos.yaw * DEG)}&lat=${pos.pitch * DEG}&fov=${fov}&${query()}`;
  const r = await fetch(`api/auto-exposure?${q}`);
  if (r.ok) { setEv(Math.round((await r.json()).ev * 4) / 4); reload(); }
});

if (info.slots.length > 1) {
  $('time-row').hidden = false;
  $('time').max = String(info.slots.length - 1);
  $('time-value').textContent = info.slots[0].label;
  $('time').addEventListener('input', () => { $('time-value').textContent = info.slots[Number($('time').value)].label; });
  $('time').addEventListener('change', () => {
    state.t = Number($('time').value);
    reload();
    refreshProbes();
  });
}

// ------------------------------------------------------------------ probes
function wrapLon(deg) { return ((deg + 180) % 360 + 360) % 360 - 180; }

let shiftDown = false;
$('viewer').addEventListener('pointerdown', (e) => { shiftDown = e.shiftKey; }, true);

viewer.addEventListener('click', ({ data }) => {
  if (data.rightclick) return;
  const second = shiftDown || $('second').checked;
  $('second').checked = false;
  const point = { lon: wrapLon(data.yaw * DEG), lat: data.pitch * DEG };
  state.points[second ? 1 : 0] = point;
  placeMarkers();
  refreshProbes();
});

// probe markers: plain elements over the canvas, placed at every rendered frame
const markers = [0, 1].map((i) => {
  const m = document.createElement('div');
  m.className = `marker p${i + 1}`;
  m.textContent = String(i + 1);
  m.hidden = true;
  $('viewer').appendChild(m);
  return m;
});
function placeMarkers() {
  state.points.forEach((p, i) => {
    const pos = p && { yaw: p.lon / DEG, pitch: p.lat / DEG };
    const visible = pos && viewer.dataHelper.isPointVisible(pos);
    markers[i].hidden = !visible;
    if (visible) {
      const xy = viewer.dataHelper.sphericalCoordsToViewerCoords(pos);
      markers[i].style.transform = `translate(${xy.x}px, ${xy.y}px)`;
    }
  });
}
viewer.addEventListener('render', placeMarkers);

async function fetchProbe(point) {
  const r = await fetch(`api/spectrum?lon=${point.lon}&lat=${point.lat}&t=${state.t}`);
  const body = await r.json();
  return r.ok ? body : { error: body.error, lon_deg: point.lon, lat_deg: point.lat, slot: state.t };
}

async function refreshProbes() {
  omni.probes = await Promise.all(state.points.map((p) => (p ? fetchProbe(p) : null)));
  showProbes();
  if (info.slots.length > 1 && state.points[0]) {
    const p = state.points[0];
    omni.day = (await (await fetch(`api/spectrum?lon=${p.lon}&lat=${p.lat}&all=1`)).json()).slots;
    showDay();
  }
  omni.probeVersion = (omni.probeVersion ?? 0) + 1;
}

function fmt(v, d = 4) { return v === null || v === undefined ? 'n/a' : Number(v).toPrecision(d); }

function showProbes() {
  const text = $('probe-text');
  text.innerHTML = '';
  const ok = [];
  omni.probes.forEach((p, i) => {
    if (!p) return;
    const div = document.createElement('div');
    div.className = `p${i + 1}`;
    div.dataset.probe = String(i + 1);
    if (p.error) {
      div.textContent = `P${i + 1}: lon ${p.lon_deg.toFixed(2)}°, lat ${p.lat_deg.toFixed(2)}°: ${p.error}`;
    } else {
      div.textContent = `P${i + 1}: lon ${p.lon_deg.toFixed(2)}°, lat ${p.lat_deg.toFixed(2)}°, `
        + `CIE x ${fmt(p.xy[0])}, y ${fmt(p.xy[1])}`;
      ok.push([i, p]);
    }
    text.appendChild(div);
  });
  drawChart($('chart'), ok.map(([i, p]) => ({
    x: p.wavelength_nm, y: p.spectrum, sigma: p.std, color: COLORS[i], width: 2,
  })), 'wavelength (nm)', `estimate ± 2σ (${info.units})`);
  const table = $('bands-table');
  table.innerHTML = '';
  if (ok.length) {
    const head = table.insertRow();
    ['band', ...ok.map(([i]) => `P${i + 1}`)].forEach((h) => { const th = document.createElement('th'); th.textContent = h; head.appendChild(th); });
    info.bands.forEach((b) => {
      const row = table.insertRow();
      row.insertCell().textContent = b;
      ok.forEach(([i, p]) => { const c = row.insertCell(); c.className = `p${i + 1}`; c.textContent = fmt(p.bands[b], 5); });
    });
  }
  const points = state.points.filter((p) => p);
  $('csv').hidden = points.length === 0;
  $('csv').href = `api/probes.csv?t=${state.t}&${points.map((p) => `p=${p.lon},${p.lat}`).join('&')}`;
}

function showDay() {
  const svg = $('day-chart');
  svg.hidden = false;
  const n = omni.day.length;
  const series = omni.day.filter((s) => !s.error).map((s) => {
    const f = n > 1 ? s.slot / (n - 1) : 0;
    return {
      x: s.wavelength_nm, y: s.spectrum, color: `hsl(${240 - 200 * f}, 80%, ${s.slot === state.t ? 70 : 50}%)`,
      width: s.slot === state.t ? 3 : 1.2, label: s.label,
    };
  });
  drawChart(svg, series, 'wavelength (nm)', 'P1 over the day');
}

// ------------------------------------------------------------------ plain SVG charts
function niceTicks(lo, hi, n) {
  const step0 = (hi - lo) / n;
  const mag = 10 ** Math.floor(Math.log10(step0));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= step0);
  const ticks = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) ticks.push(v);
  return ticks;
}

function drawChart(svg, series, xlabel, ylabel) {
  const NS = 'http://www.w3.org/2000/svg';
  const W = Number(svg.getAttribute('width')), H = Number(svg.getAttribute('height'));
  const m = { l: 48, r: 8, t: 14, b: 30 };
  svg.innerHTML = '';
  const el = (name, attrs, text) => {
    const e = document.createElementNS(NS, name);
    Object.entries(attrs).forEach(([k, v]) => e.setAttribute(k, v));
    if (text !== undefined) e.textContent = text;
    svg.appendChild(e);
    return e;
  };
  if (!series.length) return;
  const xs = series[0].x;
  let ymax = 0;
  series.forEach((s) => s.y.forEach((v, j) => { ymax = Math.max(ymax, v + 2 * (s.sigma ? s.sigma[j] : 0)); }));
  ymax = ymax > 0 ? ymax * 1.05 : 1;
  const X = (v) => m.l + (v - xs[0]) / (xs[xs.length - 1] - xs[0]) * (W - m.l - m.r);
  const Y = (v) => H - m.b - Math.max(0, v) / ymax * (H - m.t - m.b);
  niceTicks(0, ymax, 4).forEach((v) => {
    el('line', { class: 'grid', x1: m.l, x2: W - m.r, y1: Y(v), y2: Y(v) });
    el('text', { x: m.l - 4, y: Y(v) + 3, 'text-anchor': 'end' }, Number(v.toPrecision(3)).toExponential(1));
  });
  niceTicks(xs[0], xs[xs.length - 1], 6).forEach((v) => {
    el('text', { x: X(v), y: H - m.b + 12, 'text-anchor': 'middle' }, String(v));
  });
  el('path', { class: 'axis', d: `M${m.l},${m.t}V${H - m.b}H${W - m.r}` });
  el('text', { x: (m.l + W - m.r) / 2, y: H - 4, 'text-anchor': 'middle' }, xlabel);
  el('text', { x: m.l, y: 10 }, ylabel);
  series.forEach((s) => {
    if (s.sigma) {
      const up = s.x.map((x, j) => `${X(x)},${Y(s.y[j] + 2 * s.sigma[j])}`);
      const down = s.x.map((x, j) => `${X(x)},${Y(s.y[j] - 2 * s.sigma[j])}`).reverse();
      el('polygon', { points: [...up, ...down].join(' '), fill: s.color, 'fill-opacity': 0.22, stroke: 'none' });
    }
    el('polyline', { points: s.x.map((x, j) => `${X(x)},${Y(s.y[j])}`).join(' '), fill: 'none',
      stroke: s.color, 'stroke-width': s.width, class: 'curve' });
  });
}

omni.ready = true;
