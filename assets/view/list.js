// The job list: state, progress and headline figures, refreshed every two
// seconds while a job runs, and now and then otherwise for jobs submitted
// since.
import { takeFragmentToken, getJson } from './auth.js';

takeFragmentToken();
const REFRESH_MS = 2000;
const IDLE_REFRESH_MS = 15000;
// The states each job was shown in, in order, for a driving browser.
const shown = {};
window.seamstressShown = shown;
const status = document.getElementById('status');
const body = document.querySelector('#jobs tbody');

function cell(tr, text) {
  const td = document.createElement('td');
  td.textContent = text;
  tr.append(td);
  return td;
}

/** "8.70 → 0.39" over the report's textures' closed seams, the worst first. */
function headline(report) {
  if (!report || !report.textures) return '';
  return report.textures.map((t) => {
    const shipped = t.bc1_seam_aware || t.bc7_seam_aware || t.bc1 || t.bc7 || t.erased;
    const f = (m) => (m && m.seam_rms_closed != null ? m.seam_rms_closed.toFixed(2) : '–');
    return `${t.name}: ${f(t.input)} → ${f(shipped)}`;
  }).join('; ');
}

/** Headlines of finished jobs, which do not change: asked for once each. */
const headlines = new Map();

async function headlineOf(job) {
  if (job.state !== 'succeeded') return ['', ''];
  if (!headlines.has(job.id)) {
    const full = await getJson(`/v1/jobs/${encodeURIComponent(job.id)}`);
    const textures = full.report && full.report.textures ? String(full.report.textures.length) : '';
    headlines.set(job.id, [textures, headline(full.report)]);
  }
  return headlines.get(job.id);
}

async function refresh() {
  let list;
  try {
    list = await getJson('/v1/jobs?limit=100');
  } catch (e) {
    status.textContent = String(e);
    setTimeout(refresh, REFRESH_MS * 5);
    return;
  }
  // The finished jobs' headlines asked for together, not one at a time.
  const heads = await Promise.all(list.jobs.map((job) => headlineOf(job).catch(() => ['', ''])));
  body.replaceChildren();
  let running = 0;
  list.jobs.forEach((job, k) => {
    const states = shown[job.id] || (shown[job.id] = []);
    if (states[states.length - 1] !== job.state) states.push(job.state);
    const tr = document.createElement('tr');
    cell(tr, job.id.slice(0, 12));
    cell(tr, job.input ? job.input.name : '');
    cell(tr, job.state).className = 'state-' + job.state;
    const fraction = job.progress ? job.progress.fraction : 0;
    const p = cell(tr, '');
    const bar = document.createElement('progress');
    bar.max = 1;
    bar.value = fraction;
    p.append(bar, ` ${(fraction * 100).toFixed(0)}% ${job.progress ? job.progress.stage : ''}`);
    const [textures, figures] = heads[k];
    cell(tr, textures);
    cell(tr, figures);
    const link = cell(tr, '');
    // The page of a job still running shows its progress, then its model.
    if (job.state === 'succeeded' || job.state === 'queued' || job.state === 'running') {
      const a = document.createElement('a');
      a.href = `/v1/jobs/${encodeURIComponent(job.id)}/view`;
      a.textContent = 'view';
      link.append(a);
    }
    if (job.state === 'queued' || job.state === 'running') running += 1;
    body.append(tr);
  });
  status.textContent = `${list.jobs.length} jobs` + (running ? `, ${running} in progress (refreshing)` : '');
  setTimeout(refresh, running ? REFRESH_MS : IDLE_REFRESH_MS);
}

refresh();
