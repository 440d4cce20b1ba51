// The viewer's two benchmarks (docs/viewer.md), printed as tables and written as CSV:
//   tick  the zone's tick p50/p99 with and without a viewer open, in alternating phases of one
//         zone-server process (its --tick-csv), at --npcs entities;
//   fps   the page's frames a second while it pans (window.zoneViewer.benchmark), in headless
//         chromium with software WebGL, at --npcs entities: every entity drawn one by one, and
//         the default point budget (a density grid when zoomed out).
// Needs what the browser test needs (scripts/setup.sh: chromium, tests/viewer/node_modules).
//
// Usage: node tools/viewer_bench.mjs tick --server build/zone/zone-server [--npcs 20000]
//          [--phase-s 20] [--rounds 3] [--viewer page|socket] [--csv FILE]
//        node tools/viewer_bench.mjs fps --server build/zone/zone-server [--npcs 100000] [--seconds 8]
//          [--server-args "--tick-rate 5 --threads 1"] [--pause-server 1] [--csv FILE] [--screenshot PREFIX.png]
import { spawn } from 'node:child_process';
import { existsSync, readFileSync, writeFileSync, mkdtempSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { dirname, join } from 'node:path';
import { fileURLToPath } from 'node:url';

const here = dirname(fileURLToPath(import.meta.url));
const [mode, ...rest] = process.argv.slice(2);
const args = {};
for (let i = 0; i < rest.length; ++i) if (rest[i].startsWith('--')) args[rest[i].slice(2)] = rest[i + 1];
if (!['tick', 'fps'].includes(mode) || !args.server) {
  console.log('usage: node tools/viewer_bench.mjs tick|fps --server ZONE_SERVER [--npcs N] [--phase-s S] [--rounds R] [--viewer page|socket] [--seconds S] [--server-args "ARGS"] [--pause-server 1] [--csv FILE] [--screenshot PREFIX.png]');
  process.exit(mode === '--help' || mode === 'help' ? 0 : 2);
}
const chromiumPath = args.chromium || process.env.ZONE_CHROMIUM || '/usr/bin/chromium';
if (!existsSync(chromiumPath)) { console.error(`no chromium at ${chromiumPath} (scripts/setup.sh)`); process.exit(1); }
const { chromium } = await import(join(here, '..', 'tests', 'viewer', 'node_modules', 'playwright-core', 'index.mjs'));
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
const children = [];
process.on('exit', () => { for (const c of children) if (c.exitCode === null) c.kill('SIGTERM'); });
for (const sig of ['SIGINT', 'SIGTERM']) process.on(sig, () => process.exit(1));

function startServer(extra) {
  const child = spawn(args.server, ['--listen', '127.0.0.1', '--port', '0', '--metrics-port', '0', '--viewer', '1', ...extra],
                      { stdio: ['ignore', 'pipe', 'pipe'] });
  children.push(child);
  let log = '';
  return new Promise((resolve, reject) => {
    const on = (d) => {
      log += d.toString();
      const m = log.match(/viewer on http:\/\/[0-9.]+:(\d+)\/viewer/);
      if (m) resolve({ child, http: Number(m[1]) });
    };
    child.stdout.on('data', on); child.stderr.on('data', on);
    child.on('exit', (code) => reject(new Error(`zone-server exited with ${code}:\n${log}`)));
  });
}
const browserArgs = ['--no-sandbox', '--enable-unsafe-swiftshader', '--use-angle=swiftshader'];
function pct(sorted, q) { return sorted.length ? sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))] : NaN; }

if (mode === 'tick') {
  const npcs = Number(args.npcs || 20000), phaseS = Number(args['phase-s'] || 20), rounds = Number(args.rounds || 3);
  const viewerKind = args.viewer || 'page';
  const csvTicks = join(mkdtempSync(join(tmpdir(), 'viewer-bench-')), 'ticks.csv');
  const srv = await startServer(['--npcs', String(npcs), '--tick-csv', csvTicks, '--log-level', 'info']);
  const t0 = Date.now();  // the loop's first tick (t_s = 0 in the CSV) follows within milliseconds
  const browser = await chromium.launch({ executablePath: chromiumPath, args: browserArgs });
  const phases = [];
  const publishMs = [];  // the tick's own viewer phase (publish_viewer), per tick, from the stats messages
  const now = () => (Date.now() - t0) / 1000;
  await sleep(5000);  // warm-up (first ticks, allocation)
  for (let r = 0; r < rounds; ++r) {
    for (const open of [false, true]) {
      let page = null;
      if (open) {
        page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
        if (viewerKind === 'page') {
          await page.goto(`http://127.0.0.1:${srv.http}/viewer`);
        } else {
          // A socket that reads every frame and draws nothing: the server's side alone.
          await page.goto(`http://127.0.0.1:${srv.http}/viewer/entity.json?id=1`).catch(() => {});
          await page.evaluate((port) => {
            const ws = new WebSocket(`ws://127.0.0.1:${port}/viewer/ws`); ws.binaryType = 'arraybuffer';
            window.frames_in = 0; window.viewer_ms = [];
            ws.onmessage = (e) => {
              window.frames_in++;
              if (typeof e.data === 'string') { const s = JSON.parse(e.data); for (const t of s.ticks || []) window.viewer_ms.push(t[6]); }
            };
            ws.onopen = () => { const b = new ArrayBuffer(28), dv = new DataView(b); dv.setUint8(0, 1);
              [0, 0, 4096, 4096].forEach((v, i) => dv.setFloat32(4 + 4 * i, v, true)); dv.setUint32(24, 1 << 20, true); ws.send(b); };
          }, srv.http);
        }
        await sleep(1000);  // connected and streaming before the phase starts
      }
      const from = now();
      await sleep(phaseS * 1000);
      phases.push({ round: r + 1, viewer: open, from, to: now() });
      if (page && viewerKind === 'socket') publishMs.push(...(await page.evaluate(() => window.viewer_ms)));
      if (page) await page.close();
      await sleep(1000);
    }
  }
  await browser.close();
  srv.child.kill('SIGTERM');
  await sleep(500);
  // t_s in the CSV counts from the first tick; the phases from just after the server was up.
  const rows = readFileSync(csvTicks, 'utf8').trim().split('\n').slice(1).map((l) => l.split(',').map(Number));
  const firstWall = 0;  // the two clocks start within milliseconds; a phase starts a second after the page opened
  const table = [];
  const all = { false: [], true: [] };
  for (const p of phases) {
    const ms = rows.filter((r) => r[1] >= p.from + firstWall && r[1] < p.to + firstWall).map((r) => r[10]).sort((a, b) => a - b);
    all[p.viewer].push(...ms);
    table.push({ round: p.round, viewer: p.viewer ? viewerKind : 'none', ticks: ms.length, p50: pct(ms, 0.5), p99: pct(ms, 0.99), max: ms[ms.length - 1] });
  }
  for (const v of [false, true]) {
    const ms = all[v].sort((a, b) => a - b);
    table.push({ round: 'all', viewer: v ? viewerKind : 'none', ticks: ms.length, p50: pct(ms, 0.5), p99: pct(ms, 0.99), max: ms[ms.length - 1] });
  }
  console.log(`tick_ms of zone-server --npcs ${npcs} (${rows.length} ticks), phases of ${phaseS} s, viewer: ${viewerKind}`);
  console.log('round  viewer  ticks    p50_ms   p99_ms   max_ms');
  for (const t of table) console.log(`${String(t.round).padEnd(6)} ${t.viewer.padEnd(7)} ${String(t.ticks).padStart(6)} ${t.p50.toFixed(3).padStart(9)} ${t.p99.toFixed(3).padStart(8)} ${t.max.toFixed(3).padStart(8)}`);
  const a = table.find((t) => t.round === 'all' && t.viewer === 'none'), b = table.find((t) => t.round === 'all' && t.viewer !== 'none');
  console.log(`p99 change with the viewer open: ${((b.p99 / a.p99 - 1) * 100).toFixed(1)}%`);
  if (publishMs.length) {
    const v = publishMs.sort((x, y) => x - y);
    console.log(`the tick's viewer phase (snapshot and stats), ${v.length} ticks: p50 ${pct(v, 0.5).toFixed(3)} ms, p99 ${pct(v, 0.99).toFixed(3)} ms, max ${v[v.length - 1].toFixed(3)} ms` +
                ` = ${(pct(v, 0.99) / a.p99 * 100).toFixed(2)}% of the tick p99 without a viewer`);
  }
  if (args.csv) writeFileSync(args.csv, 'round,viewer,ticks,p50_ms,p99_ms,max_ms\n' + table.map((t) => [t.round, t.viewer, t.ticks, t.p50, t.p99, t.max].join(',')).join('\n') + '\n');
} else {
  const npcs = Number(args.npcs || 100000), seconds = Number(args.seconds || 8), pause = args['pause-server'] === '1';
  const extra = args['server-args'] ? args['server-args'].split(' ').filter(Boolean) : [];
  const srv = await startServer(['--npcs', String(npcs), '--log-level', 'info', ...extra]);
  const browser = await chromium.launch({ executablePath: chromiumPath, args: browserArgs });
  const results = [];
  for (const [label, max, zoom] of [['every entity', 1 << 20, 1], ['default budget', 0, 1], ['zoomed in 4x', 0, 4]]) {
    const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
    await page.goto(`http://127.0.0.1:${srv.http}/viewer${max ? `?max=${max}` : ''}`);
    await page.waitForFunction(() => window.zoneViewer && window.zoneViewer.state.total > 0 && window.zoneViewer.state.mode, null, { timeout: 120000 });
    if (zoom > 1) {
      // A quarter of the world's width around its centre (the page asks for half a screen more
      // on every side): the entities there are drawn one by one.
      await page.evaluate((z) => { const w = window.zoneViewer.state.world, cx = (w[0] + w[2]) / 2, cy = (w[1] + w[3]) / 2, h = (w[2] - w[0]) / z / 2;
                                   window.zoneViewer.setView(cx - h, cy - h * 0.625, cx + h, cy + h * 0.625); }, zoom);
      await page.waitForFunction(() => window.zoneViewer.state.mode === 'entities', null, { timeout: 120000 });
    }
    await sleep(2000);
    const f0 = await page.evaluate(() => window.zoneViewer.state.frames);
    // --pause-server 1: the server is stopped (SIGSTOP) while the page pans, so that the page has
    // the 2 cores to itself, as a browser on another machine would; the last frame stays drawn.
    if (pause) srv.child.kill('SIGSTOP');
    const r = await page.evaluate((s) => window.zoneViewer.benchmark(s), seconds);
    if (pause) srv.child.kill('SIGCONT');
    const f1 = await page.evaluate(() => window.zoneViewer.state.frames);
    const total = await page.evaluate(() => window.zoneViewer.state.total);
    results.push({ label, ...r, total, snapshots_per_s: (f1 - f0) / r.seconds });
    await page.close();
  }
  if (args.screenshot) {
    // The whole world (the density grid), then a town zoomed in with its busiest entity selected.
    const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
    await page.goto(`http://127.0.0.1:${srv.http}/viewer`);
    await page.waitForFunction(() => window.zoneViewer && window.zoneViewer.state.mode === 'density grid', null, { timeout: 120000 });
    await page.waitForFunction(() => window.zoneViewer.state.stats, null, { timeout: 60000 });
    await sleep(1500);
    await page.screenshot({ path: args.screenshot.replace(/\.png$/, '') + '-world.png' });
    // The densest cell of the grid: a town.
    const town = await page.evaluate(() => {
      const v = window.zoneViewer; return v.densest();
    });
    await page.evaluate((t) => window.zoneViewer.setView(t[0] - 150, t[1] - 95, t[0] + 150, t[1] + 95), town);
    await page.waitForFunction(() => window.zoneViewer.state.mode === 'entities' && window.zoneViewer.state.decoded > 0, null, { timeout: 60000 });
    const id = await page.evaluate((t) => {
      const v = window.zoneViewer; let best = 0, bestD = Infinity;
      for (const e of v.entityIds()) { const p = v.positionOf(e); const d = (p[0] - t[0]) ** 2 + (p[1] - t[1]) ** 2; if (p[2] === 1 && d < bestD) { bestD = d; best = e; } }
      v.select(best); return best;
    }, town);
    await page.waitForFunction(() => window.zoneViewer.state.selection, null, { timeout: 60000 });
    await sleep(4000);  // a few stats messages for the strip
    await page.screenshot({ path: args.screenshot.replace(/\.png$/, '') + '-town.png' });
    console.log(`screenshots: ${args.screenshot.replace(/\.png$/, '')}-world.png, -town.png (entity ${id} selected)`);
    await page.close();
  }
  await browser.close();
  console.log(`page frames a second while panning, zone-server --npcs ${npcs} ${extra.join(' ')}${pause ? ' (paused while panning)' : ''}, headless chromium (software WebGL), 1280x800`);
  console.log('view            entities  drawn_as       drawn   fps   messages_per_s');
  for (const r of results) console.log(`${r.label.padEnd(15)} ${String(r.total).padStart(8)}  ${r.mode.padEnd(13)} ${String(r.drawn).padStart(6)} ${r.fps.toFixed(1).padStart(5)} ${r.snapshots_per_s.toFixed(1).padStart(8)}`);
  if (args.csv) writeFileSync(args.csv, 'view,entities,drawn_as,drawn,fps,messages_per_s\n' + results.map((r) => [r.label, r.total, r.mode, r.drawn, r.fps.toFixed(2), r.snapshots_per_s.toFixed(2)].join(',')).join('\n') + '\n');
}
process.exit(0);
