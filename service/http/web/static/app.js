// oarmreg OR status page.  Plain ES2020, no framework, no build step, same origin only.
// The API token comes from the sign-in form or the URL fragment (#token=…, which never reaches the
// server), lives in sessionStorage (this tab only), and travels as "Authorization: Bearer"; never a
// cookie.  Live updates: POST /events/ticket, then EventSource("/events?ticket=…").
// Every text from the service is put in the page with textContent (never innerHTML).
"use strict";

const TOKEN_KEY = "oarmreg.token";
const EVENTS = [
  "scan_arrived", "scan_invalid", "scan_reopened", "scan_files_deleted", "scan_state",
  "registration_done", "registration_refused", "registration_withdrawn", "registration_retired",
  "verification_done", "link_state", "calibration_progress", "calibration_done",
  "calibration_refused", "calibration_activated",
];
const STATUS_POLL_MS = 2000;  // the link's frame age and joints change continuously
const RECONNECT_MS = 2000;    // after the event stream drops, a new ticket and stream
const REFRESH_DEBOUNCE_MS = 50;
const VER_PAGE = 10;
const QA_FETCH = 1000;  // GET /qa/trend's page limit; the chart shows the newest QA_SHOWN checks
const QA_SHOWN = 40;

const state = {
  token: null, es: null, statusTimer: null, refreshTimer: null, reconnectTimer: null,
  verOffset: 0, verSelected: null, calSelected: null, calArmed: false,
  current: null, withdrawal: null, registrations: [], calibrations: [], gates: {},
};

const $ = (id) => document.getElementById(id);

function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "class") e.className = v; else if (k === "dataset") Object.assign(e.dataset, v);
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return e;
}

const SVG_NS = "http://www.w3.org/2000/svg";
function svg(tag, attrs, ...children) {
  const e = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, String(v));
  for (const c of children) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return e;
}

function fmt(v, digits = 4) {
  return v === null || v === undefined || Number.isNaN(v) ? "—" : Number(v).toFixed(digits);
}
function when(iso) {
  if (!iso) return "—";
  const d = new Date(iso);
  return Number.isNaN(d.getTime()) ? iso : d.toLocaleString();
}
function setText(id, text, value) {
  const e = $(id);
  e.textContent = text;
  if (value !== undefined) e.dataset.value = value === null ? "" : String(value);
}

// ---- sign-in ----------------------------------------------------------------------------------

function tokenFromFragment() {
  const m = /^#token=([^&]+)/.exec(location.hash);
  if (!m) return null;
  history.replaceState(null, "", location.pathname + location.search);  // out of the address bar
  return decodeURIComponent(m[1]);
}

async function api(path, opts = {}) {
  const headers = { Authorization: "Bearer " + state.token, ...(opts.headers || {}) };
  if (opts.method === "POST") headers["Content-Type"] = "application/json";
  const r = await fetch(path, { ...opts, headers, cache: "no-store", credentials: "omit" });
  const ctype = r.headers.get("content-type") || "";
  const body = ctype.includes("json") ? await r.json() : await r.text();
  if (r.status === 401) signOut("The service refused the token: " + (body.detail || r.status));
  return { ok: r.ok, status: r.status, body };
}

async function signIn(token) {
  state.token = token;
  const r = await fetch("/status", { headers: { Authorization: "Bearer " + token }, cache: "no-store" });
  if (r.status === 401) { signOut("The service refused this token; check api_token."); return; }
  sessionStorage.setItem(TOKEN_KEY, token);
  $("sign-in").hidden = true;
  $("app").hidden = false;
  $("sign-out").hidden = false;
  await refreshAll();
  connectEvents();
  state.statusTimer = setInterval(() => refreshStatus().catch(showFailure), STATUS_POLL_MS);
}

function signOut(message) {
  sessionStorage.removeItem(TOKEN_KEY);
  state.token = null;
  if (state.es) { state.es.close(); state.es = null; }
  clearInterval(state.statusTimer);
  clearTimeout(state.reconnectTimer);
  setLive(false);
  $("app").hidden = true;
  $("sign-out").hidden = true;
  $("sign-in").hidden = false;
  $("sign-in-error").textContent = message || "";
}

// ---- live updates -----------------------------------------------------------------------------

function setLive(on, text) {
  const p = $("live");
  p.className = "pill " + (on ? "ok" : "off");
  p.textContent = text || (on ? "live" : "offline");
}

async function connectEvents() {
  if (!state.token) return;
  let r;
  try { r = await api("/events/ticket", { method: "POST" }); } catch (e) { r = { ok: false }; }
  if (!r.ok) { scheduleReconnect(); return; }
  const es = new EventSource(r.body.url);
  state.es = es;
  es.onopen = () => { setLive(true); scheduleRefresh(); };
  es.onerror = () => { es.close(); if (state.es === es) { state.es = null; scheduleReconnect(); } };
  for (const name of EVENTS) es.addEventListener(name, scheduleRefresh);
  es.onmessage = scheduleRefresh;
}

function scheduleReconnect() {
  setLive(false, "reconnecting");
  clearTimeout(state.reconnectTimer);
  if (state.token) state.reconnectTimer = setTimeout(connectEvents, RECONNECT_MS);
}

function scheduleRefresh() {
  clearTimeout(state.refreshTimer);
  state.refreshTimer = setTimeout(() => refreshAll().catch(showFailure), REFRESH_DEBOUNCE_MS);
}

function showFailure(e) {
  setLive(false, "service unreachable");
  $("banners").replaceChildren(banner("bad", "The page cannot reach the service: " + e,
    "Check that oarmreg serve is running on this machine; the page retries by itself."));
}

// ---- loading ------------------------------------------------------------------------------------

async function refreshAll() {
  if (!state.token) return;
  const [st, regs, scans, vers, cals] = await Promise.all([
    api("/status"), api("/registrations?limit=20"), api("/scans?limit=20"),
    api(`/verifications?limit=${VER_PAGE + 1}&offset=${state.verOffset}`), api("/calibrations?limit=20"),
  ]);
  const qa = await api(`/qa/trend?limit=${QA_FETCH}`);
  if (!st.ok) return;
  state.registrations = regs.ok ? regs.body : [];
  state.calibrations = cals.ok ? cals.body : [];
  // /status carries the current registration as GET /registration/current gives it (registration_out):
  // one snapshot, so a withdrawal between two requests cannot answer 409 (a console error) here
  const current = st.body.current_registration || null;
  state.current = current;
  state.withdrawal = st.body.registration_withdrawal || null;
  state.gates = st.body.gates || {};
  renderStatus(st.body);
  await renderJoints(st.body);
  renderCurrent(current);
  renderRegistrations(state.registrations);
  renderScans(scans.ok ? scans.body : []);
  renderVerifications(vers.ok ? vers.body : []);
  renderCalibrations(state.calibrations);
  if (qa.ok) renderQa(qa.body);
  renderBanners(st.body, current, state.registrations);
  await renderAlarm(current ? null : state.withdrawal);
}

async function refreshStatus() {
  if (!state.token) return;
  const st = await api("/status");
  if (!st.ok) return;
  renderStatus(st.body);
  await renderJoints(st.body);
}

// ---- plain words ------------------------------------------------------------------------------

const ADVICE = [
  [/moved|still/i, "Keep the robot still for the whole scan, then scan again and register again."],
  [/link|joint|frame/i, "Check the robot controller connection (Status: robot link), then scan and register again."],
  [/too few|spheres|detect/i, "Make sure the whole phantom is inside the scan's field of view and nothing covers it; scan again."],
  [/ambiguous|symmetr|mirror/i, "The phantom's pose could not be told apart from a symmetric one: turn the phantom so more spheres are visible, scan again."],
  [/FRE|gate|residual/i, "The fit is worse than the quality gate: check the phantom, the rod and the robot model; scan again."],
  [/incomplete|reopen|late slices|withdrawn/i, "The scan changed after it was registered: wait for the export to finish, then register again."],
  [/calibration/i, "A calibration was activated: register again with a new scan."],
  [/DICOM|series|slice|geometry/i, "The scan itself is unusable: export it again from the O-arm."],
];
function advice(text) {
  for (const [re, what] of ADVICE) if (re.test(text)) return what;
  return "Read the reason, fix the cause, scan again and register again.";
}
// Actions in the OR's words: an API call or a docs path in parentheses moves into a tooltip ("how?").
const API_ASIDE = /\s*\(([^()]*(?:\b(?:GET|POST) \/|docs\/)[^()]*)\)/g;
function orWords(text) {
  const asides = [];
  const plain = String(text || "").replace(API_ASIDE, (_m, inner) => { asides.push(inner.trim()); return ""; });
  return { plain, api: asides.join("; ") };
}
function inOrWords(text) {
  const { plain, api } = orWords(text);
  const out = el("span", {}, plain);
  if (api) out.append(" ", el("abbr", { class: "api", title: api }, "how?"));
  return out;
}
function banner(cls, text, what) {
  return el("div", { class: "banner " + cls }, inOrWords(text),
    what ? el("span", { class: "what" }, "What to do: ", inOrWords(what)) : "");
}

function noCurrentReason(regs) {
  const v = state.withdrawal;
  if (v) return `Registration ${v.registration_id} was withdrawn: ${v.reason}.`;
  const w = regs.find((r) => r.status === "withdrawn" || r.status === "retired");
  if (w) {
    return `Registration ${w.id} was ${w.status}: ${w.reason || "retired by a calibration"}`;
  }
  return "No registration has been accepted yet.";
}

function renderBanners(st, current, regs) {
  const out = [];
  $("alarm-banner").replaceChildren();
  const withdrawal = st.registration_withdrawal;
  for (const p of st.problem_details || []) {
    if (p.type === "registration-withdrawn") continue;  // its own banner below, with cause and action
    if (p.type === "qa-drift") {
      const b = banner("warn", `${p.title}: ${p.detail}`,
        "Run a calibration session, activate it, then repeat the QA protocol (QA trend below).");
      b.id = "recalibrate-banner";
      out.push(b);
    } else {
      out.push(banner("bad", "Service problem: " + p.detail, null));
    }
  }
  if (!current && withdrawal) {
    const v = withdrawal;
    const what = v.verification_id == null
      ? `the verification of scan ${v.verification_scan_id} could not be computed (the error is beyond what matching can bridge)`
      : `verification ${v.verification_id} (scan ${v.verification_scan_id}) failed the ${fmt(v.gate_mm, 2)} mm gate`;
    // one sentence per fact; the cause's full reasoning in a tooltip
    const shortCause = String(v.cause).split(":")[0];
    const b = banner("bad", `No current registration: navigation must not use an old matrix. Registration ` +
      `${v.registration_id} was withdrawn: ${what}.`, v.action.charAt(0).toUpperCase() + v.action.slice(1) + ".");
    b.insertBefore(el("span", { class: "cause", title: v.cause }, ` Likely cause: ${shortCause}.`), b.querySelector(".what"));
    b.id = "withdrawn-banner";
    b.dataset.cause = v.likely_cause;
    $("alarm-banner").replaceChildren(b);  // at the top, with the failed verification's histogram
  } else if (!current) {
    const reason = noCurrentReason(regs);
    out.push(banner("bad", "No current registration: navigation must not use an old matrix. " + reason,
      /accepted yet/.test(reason) ? "Scan the phantom and register it (POST /register)." : advice(reason)));
  }
  const newest = regs[0];
  if (newest && newest.status === "refused" && (!current || newest.id > current.id)) {
    const t = `Registration ${newest.id} (scan ${newest.scan_id}) was refused: ${newest.problem_title || "refused"}` +
      (newest.reason ? ` — ${newest.reason}` : "") +
      (current ? `. Registration ${current.id} stays current.` : ".");
    out.push(banner("bad", t, advice(newest.problem_title + " " + newest.reason)));
  }
  if (st.link && st.link.state !== "connected") {
    out.push(banner("warn", `Robot link ${st.link.state}: ${st.link.reason || ""}`,
      "Registrations are refused until the controller streams joint angles again."));
  }
  $("banners").replaceChildren(...out);
}

// After a failed verification: its banner (cause, action), verdict and histogram together at the top.
async function renderAlarm(withdrawal) {
  const alarm = $("alarm");
  alarm.hidden = !withdrawal;
  if (!withdrawal) { $("alarm-title").textContent = ""; $("alarm-chart").replaceChildren(); return; }
  const id = withdrawal.verification_id;
  const r = id == null ? { ok: false } : await api(`/verifications/${id}`);
  if (!r.ok) {
    $("alarm-title").textContent = id == null ? "The verification could not be computed." : "";
    $("alarm-chart").replaceChildren();
    return;
  }
  const v = r.body;
  const t = $("alarm-title");
  t.textContent = `Verification ${v.id} FAILED: largest sphere error ${fmt(v.max_mm, 2)} mm, gate ${fmt(v.gate_mm, 2)} mm.`;
  t.dataset.verification = v.id;
  $("alarm-chart").replaceChildren(histogram((v.errors || []).map((e) => e.error_mm), v.gate_mm, v.passed));
}

// ---- QA trend ---------------------------------------------------------------------------------

// The phantom's face offset β of the last registrations (docs/detection-settings.md): a drift is a
// phantom or scanner change.
function renderFaceOffsetTrend(fre) {
  const b = (fre || []).filter((f) => f.face_offset_mm != null).slice(-QA_SHOWN);
  setText("qa-face-offset", b.length === 0 ? "Face offset β: not fitted yet."
    : `Face offset β of the last ${b.length} registrations (mm, oldest first): ` +
      b.map((f) => `#${f.registration_id} ${fmt(f.face_offset_mm, 4)}`).join(", ") +
      " (a drift means a phantom or scanner change: docs/detection-settings.md).",
    b.length ? JSON.stringify(b.map((f) => f.face_offset_mm)) : undefined);
}

function renderQa(t) {
  renderFaceOffsetTrend(t.fre);
  const checks = t.checks.slice(-QA_SHOWN);
  const d = t.drift;
  const under = d.calibration_id == null ? "the nominal robot model" : `calibration ${d.calibration_id}`;
  const rule = `(the drift rule reads the last ${d.window}; limit ${d.limit_mm} mm, rise ${d.rise_limit_mm} mm)`;
  $("qa-drift").textContent = d.drifting
    ? `Drifting under ${under}: ${d.detail}.`
    : d.means_mm.length === 0
      ? `No QA check yet under ${under} ${rule}: verify at a QA protocol's poses (docs/operations.md).`
      : `Steady under ${under}: QA means ${d.means_mm.map((m) => fmt(m, 3)).join(", ")} mm ${rule}.`;
  $("qa-drift").className = d.drifting ? "bad" : "note";
  if (checks.length === 0) {
    $("qa-chart").replaceChildren();
    return;
  }
  $("qa-chart").replaceChildren(barChart(
    checks.map((c) => ({ label: `#${c.verification_id} ${c.pose}`, value: c.mean_mm, cls: c.passed ? "" : "bad" })),
    { title: "QA check mean error (mm), red: FAIL", unit: "mm", second: checks.map((c) => c.max_mm), secondLabel: "max" },
  ));
}

// ---- status -----------------------------------------------------------------------------------

function renderStatus(st) {
  const h = $("health");
  h.className = "pill " + (st.healthy ? "ok" : "bad");
  h.textContent = st.healthy ? "healthy" : "unhealthy";
  $("problems").replaceChildren(...(st.problems || []).map((p) => el("li", {}, inOrWords(p))));
  const link = st.link || {};
  const ls = $("link-state");
  ls.className = link.state === "connected" ? "ok" : "bad";
  ls.textContent = `${link.state || "?"} — ${link.url || ""}${link.reason ? " (" + link.reason + ")" : ""}`;
  ls.dataset.value = link.state || "";
  setText("link-age", link.last_frame_age_s == null ? "no frame received" : `${fmt(link.last_frame_age_s, 2)} s ago`);
  const w = st.watcher || {};
  const wKeys = ["mode", "running", "health", "health_reason", "series_recorded", "invalid", "last_scan_at", "last_error"];
  setText("watcher", wKeys.filter((k) => w[k] !== undefined && w[k] !== "" && w[k] !== null)
    .map((k) => `${k.replace(/_/g, " ")}: ${k.endsWith("_at") ? when(w[k]) : w[k]}`).join(", "));
  const L = st.listeners || {};
  const d = L.dicom || {};
  setText("dicom", !d.enabled ? "off" : `${d.ae_title}@${d.host}:${d.port}, associations ${d.associations ?? 0}` +
    (d.counters ? ", " + Object.entries(d.counters).map(([k, v]) => `${k} ${v}`).join(", ") : ""));
  const g = L.igtl || {};
  setText("igtl", !g.enabled ? "off" : `${g.host}:${g.port}, clients ${g.clients ?? 0}` +
    (g.counters ? ", " + Object.entries(g.counters).map(([k, v]) => `${k} ${v}`).join(", ") : ""));
  const disk = st.disk;
  if (!disk) setText("disk", "not reported by /status");
  else {
    const quota = disk.quota_mb == null ? "no quota (retention.max_disk_mb unset)"
      : `${fmt(100 * disk.scans_mb / disk.quota_mb, 0)} % of the ${fmt(disk.quota_mb, 0)} MB quota`;
    setText("disk", `scans ${fmt(disk.scans_mb, 1)} MB, ${quota}; data folder ${fmt(disk.data_dir_free_mb, 0)} MB free`,
      disk.scans_mb);
    $("disk").className = disk.quota_mb != null && disk.scans_mb > disk.quota_mb ? "bad" : "";
  }
  const ac = st.active_calibration;
  setText("active-calibration", ac ? `calibration ${ac.calibration_id} (${String(ac.calibration_hash).slice(0, 12)}), ` +
    `predicted held-out RMS ${fmt(ac.predicted_held_out_rms_mm, 3)} mm, since ${when(ac.activated_at)}`
    : "none: the nominal robot model and rod (the cell is not calibrated)");
  setText("counts", Object.entries(st.counts || {}).map(([k, v]) => `${k} ${v}`).join(", "));
  setText("service", `oarmreg ${st.version}, up ${Math.round(st.uptime_s)} s, auth ${st.auth_enabled ? "on" : "OFF"}` +
    (st.busy ? ", busy" : ""));
}

async function renderJoints(st) {
  if (!st.link || st.link.last_frame_age_s == null) { setText("joints", "—"); return; }
  const r = await api("/robot/joints");
  if (!r.ok) { setText("joints", r.body.detail || "—"); return; }
  const q = r.body.joints_rad;
  setText("joints", q.map((v, i) => `J${i + 1} ${fmt(v * 180 / Math.PI, 2)}°`).join("  "), JSON.stringify(q));
}

// ---- current registration ---------------------------------------------------------------------

function renderCurrent(cur) {
  $("current-none").hidden = !!cur;
  $("current-body").hidden = !cur;
  const badge = $("current-badge");
  if (!cur) {
    badge.className = "pill bad";
    badge.textContent = "none";
    $("current-none").textContent = noCurrentReason(state.registrations);
    return;
  }
  const level = renderEvidence(cur);
  const verdict = renderExpected(cur);
  // the same verdict as the headline and warning; never green while the robot side is unverified
  badge.textContent = level === "unverified" ? "current, unverified" : "current";
  badge.className = "pill " + (level === "unverified" && verdict.cls === "ok" ? "warn" : verdict.cls);
  setText("current-id", String(cur.id), cur.id);
  setText("current-scan", String(cur.scan_id), cur.scan_id);
  setText("current-fre", fmt(cur.fre_mm), cur.fre_mm);
  setText("current-fle", fmt(cur.fle_mm), cur.fle_mm);
  const tre = cur.predicted_tre_mm && cur.predicted_tre_mm.length ? Math.max(...cur.predicted_tre_mm) : null;
  setText("current-tre", fmt(tre), tre);
  setText("current-counts", `${cur.n_expected ?? "—"} / ${cur.n_detected ?? "—"} / ${cur.n_matched ?? "—"}`);
  setText("current-margin", `${cur.symmetry_margin ?? "—"} spheres`, cur.symmetry_margin);
  setText("current-created", when(cur.created_at));
  const rows = (cur.image_from_robot || []).map((row) => el("tr", {}, ...row.map((v) => el("td", {}, fmt(v, 6)))));
  $("current-matrix").replaceChildren(...rows);
  $("current-matrix").dataset.value = JSON.stringify(cur.image_from_robot);
  const bars = (cur.spheres || []).map((s) => ({ label: s.sphere, value: s.residual_mm }));
  $("current-chart").replaceChildren(barChart(bars, { unit: "mm", title: "residual (mm)" }));
  $("current-provenance").textContent = JSON.stringify(
    { ...cur.provenance, face_offset_mm: cur.face_offset_mm, face_offset_se_mm: cur.face_offset_se_mm }, null, 2);
}

// What backs the robot side, first (docs/safety.md, "Evidence levels"): calibrated, verified or
// unverified, one sentence, and the action when one is needed.
function renderEvidence(cur) {
  const ev = cur.evidence || { level: "unverified", summary: "", action: "" };
  const pill = $("current-evidence-level");
  pill.className = "pill " + (ev.level === "unverified" ? "warn" : "ok");
  pill.textContent = ev.level.toUpperCase();
  setText("current-evidence-text", ev.summary + (ev.action ? ` Next: ${ev.action}.` : ""));
  $("current-evidence").dataset.level = ev.level;
  return ev.level;
}

// The honest figure first: the expected error where the robot works, its gate and a one-word verdict.
// One verdict colours the headline's pill, the warning and the "current" badge.
function expectedVerdict(chain, gate, calibrated) {
  if (chain == null || gate == null) return { word: "UNKNOWN", cls: "warn" };
  if (chain >= gate) return { word: "FAIL", cls: "bad" };
  return { word: "OK", cls: calibrated ? "ok" : "warn" };
}

function renderExpected(cur) {
  const e = cur.expected_error || {};
  const chain = e.predicted_chain_error_mm ?? cur.predicted_chain_error_mm;
  const gate = state.gates.max_verification_error_mm;
  const verdict = expectedVerdict(chain, gate, !!e.calibrated);
  setText("current-chain", fmt(chain, 2), chain);
  $("current-chain").dataset.calibrated = e.calibrated ? "true" : "false";
  setText("current-gate", fmt(gate, 2), gate);
  const pill = $("current-verdict");
  pill.className = "pill " + verdict.cls;
  pill.textContent = verdict.word;
  pill.title = verdict.word === "FAIL"
    ? "A verification at another pose is expected to fail its gate (quality.max_verification_error_mm)."
    : "Below the verification gate (quality.max_verification_error_mm).";
  const basis = $("current-chain-basis");
  basis.textContent = e.calibrated ? `Calibration ${e.calibration_id} backs this figure.`
    : "Source: the nominal robot model's prior.";
  basis.title = e.basis || "";
  const warn = $("current-uncalibrated");
  warn.hidden = !!e.calibrated && verdict.cls === "ok";
  warn.className = verdict.cls;
  warn.textContent = e.calibrated
    ? (verdict.word === "FAIL" ? `Expect about ${fmt(chain, 1)} mm at the robot's working poses, above the ` +
      `${fmt(gate, 1)} mm gate. Check the calibration and verify at another pose.` : "")
    : `This cell is not calibrated. Expect about ${fmt(chain, 1)} mm at the robot's working poses. ` +
      "Calibrate the cell and activate the calibration to bring it down.";
  warn.title = e.calibrated ? "" : "docs/calibration.md";
  return verdict;
}

// ---- lists ------------------------------------------------------------------------------------

function stateCell(text, cls) { return el("td", { class: cls || "" }, text); }

function renderScans(scans) {
  $("scans-body").replaceChildren(...scans.map((s) => {
    const j = s.joints || {};
    const still = j.still === undefined ? "—" : j.still ? "yes" : "NO";
    return el("tr", { dataset: { scan: s.id } }, el("td", {}, s.id), el("td", {}, when(s.arrived_at)),
      stateCell(s.status, s.status === "complete" ? "ok" : "bad"), el("td", {}, s.n_slices),
      stateCell(still, j.still ? "ok" : "bad"), el("td", { class: "why" }, [s.reason, j.stillness_reason].filter(Boolean).join("; ")));
  }));
}

const REG_CLASS = { accepted: "ok", refused: "bad", withdrawn: "bad", retired: "warn" };
function renderRegistrations(regs) {
  $("registrations-body").replaceChildren(...regs.map((r) => {
    let what = r.is_current ? "current: navigation uses this one" : "";
    if (r.status === "refused") what = `refused: ${r.problem_title}${r.reason ? " — " + r.reason : ""}. ${advice(r.problem_title + " " + r.reason)}`;
    if (r.status === "withdrawn") what = `withdrawn: ${r.reason}`;
    if (r.status === "retired") what = `retired${r.retired_by_calibration ? " by calibration " + r.retired_by_calibration : ""}${r.reason ? ": " + r.reason : ""}`;
    if (r.status === "accepted" && !r.is_current) what = what || "accepted, superseded by a newer one";
    return el("tr", { dataset: { registration: r.id, status: r.status } }, el("td", {}, r.id), el("td", {}, r.scan_id ?? "—"),
      el("td", {}, when(r.created_at)), stateCell(r.status + (r.is_current ? " (current)" : ""), REG_CLASS[r.status]),
      el("td", {}, fmt(r.fre_mm)), el("td", {}, what));
  }));
}

function renderVerifications(vers) {
  const page = vers.slice(0, VER_PAGE);
  $("ver-prev").disabled = state.verOffset === 0;
  $("ver-next").disabled = vers.length <= VER_PAGE;
  $("ver-page").textContent = page.length ? `${state.verOffset + 1}–${state.verOffset + page.length}` : "none yet";
  $("verifications-body").replaceChildren(...page.map((v) => {
    const tr = el("tr", { dataset: { id: v.id, verification: v.id }, class: v.id === state.verSelected ? "sel" : "" },
      el("td", {}, v.id), el("td", {}, when(v.created_at)), el("td", {}, v.registration_id), el("td", {}, v.scan_id),
      el("td", {}, fmt(v.mean_mm)), el("td", {}, fmt(v.max_mm)), el("td", {}, fmt(v.gate_mm, 3)),
      stateCell(v.passed ? "PASS" : "FAIL", v.passed ? "ok" : "bad"));
    tr.addEventListener("click", () => { state.verSelected = v.id; renderVerificationDetail(v); renderVerifications(vers); });
    return tr;
  }));
  const sel = page.find((v) => v.id === state.verSelected) || page[0];
  if (sel) { state.verSelected = sel.id; renderVerificationDetail(sel); }
  $("verification-detail").hidden = !sel;
}

function renderVerificationDetail(v) {
  const t = $("ver-title");
  t.textContent = `Verification ${v.id}: scan ${v.scan_id} against registration ${v.registration_id} — ` +
    `${v.passed ? "PASS" : "FAIL"} (max ${fmt(v.max_mm, 3)} mm, gate ${fmt(v.gate_mm, 3)} mm)`;
  t.className = v.passed ? "ok" : "bad";
  t.dataset.verdict = v.passed ? "PASS" : "FAIL";
  const errors = (v.errors || []).map((e) => e.error_mm);
  $("ver-chart").replaceChildren(histogram(errors, v.gate_mm, v.passed));
  $("ver-errors").replaceChildren(...(v.errors || []).map((e) =>
    el("span", { class: e.error_mm > v.gate_mm ? "bad" : "" }, el("b", {}, e.sphere), fmt(e.error_mm))));
}

function renderCalibrations(cals) {
  $("calibrations-body").replaceChildren(...cals.map((c) => {
    const tr = el("tr", { dataset: { id: c.id, calibration: c.id }, class: c.id === state.calSelected ? "sel" : "" },
      el("td", {}, c.id), el("td", {}, when(c.created_at)),
      stateCell(c.is_active ? "active" : c.status, c.status === "refused" ? "bad" : c.is_active ? "ok" : ""),
      el("td", {}, (c.scan_ids || []).length), el("td", {}, fmt(c.predicted_held_out_rms_mm, 3)),
      el("td", {}, `${fmt(c.leave_one_pose_out_mean_mm, 3)} / ${fmt(c.leave_one_pose_out_max_mm, 3)}`),
      el("td", {}, c.status === "refused" ? c.reason : ""));
    tr.addEventListener("click", () => { state.calSelected = c.id; state.calArmed = false; renderCalibrations(state.calibrations); });
    return tr;
  }));
  const sel = cals.find((c) => c.id === state.calSelected);
  $("calibration-detail").hidden = !sel;
  if (sel) renderCalibrationDetail(sel);
}

function renderCalibrationDetail(c) {
  $("cal-title").textContent = `Calibration ${c.id}: ${c.status}${c.is_active ? " (active)" : ""}, ` +
    `fit RMS ${fmt(c.fit_rms_mm, 3)} mm, predicted held-out RMS ${fmt(c.predicted_held_out_rms_mm, 3)} mm`;
  const btn = $("cal-activate");
  const cur = state.current;
  btn.hidden = c.status !== "done" || c.is_active;
  btn.className = cur ? "danger" : "";
  const note = $("cal-activate-note");
  note.textContent = c.is_active ? "This calibration is in use for every registration." :
    c.status !== "done" ? "Only a finished calibration can be activated." :
    cur ? `Activating ends registration ${cur.id}: it is retired and navigation has no registration until the next /register.` :
    "Activating makes every later registration use this calibration (no registration is current now).";
  btn.textContent = state.calArmed && cur ? `Confirm: retire registration ${cur.id} and activate calibration ${c.id}` :
    "Activate this calibration";
  const poses = (c.poses || []);
  $("cal-pose-chart").replaceChildren(barChart(poses.map((p) => ({ label: p.name, value: p.rms_mm, cls: p.used ? "" : "bad" })),
    { unit: "mm", title: "fit RMS (mm)", second: poses.map((p) => p.leave_one_out_mean_mm), secondLabel: "leave-one-pose-out mean" }));
  const bySphere = new Map();
  for (const p of poses) (p.sphere_indices || []).forEach((k, i) => {
    const a = bySphere.get(k) || []; a.push(p.sphere_residuals_mm[i]); bySphere.set(k, a);
  });
  const spheres = [...bySphere.entries()].sort((a, b) => a[0] - b[0])
    .map(([k, a]) => ({ label: String(k), value: Math.sqrt(a.reduce((s, x) => s + x * x, 0) / a.length) }));
  $("cal-sphere-chart").replaceChildren(barChart(spheres, { unit: "mm", title: "RMS residual (mm)" }));
  $("cal-params").replaceChildren(...(c.parameters || []).map((p) =>
    el("tr", {}, el("td", {}, p.name), el("td", {}, fmt(p.value, 5)), el("td", {}, fmt(p.std_error, 5)), el("td", {}, p.unit))));
}

async function activateSelected() {
  const c = state.calibrations.find((x) => x.id === state.calSelected);
  if (!c) return;
  const cur = state.current;
  if (cur && !state.calArmed) { state.calArmed = true; renderCalibrationDetail(c); return; }
  state.calArmed = false;
  const r = await api(`/calibrations/${c.id}/activate`, { method: "POST", body: JSON.stringify({ force: !!cur }) });
  const out = $("cal-activate-result");
  out.className = r.ok ? "ok" : "bad";
  out.textContent = r.ok ? `Calibration ${c.id} is active.` + (cur ? ` Registration ${cur.id} was retired; register again.` : "")
    : `Not activated: ${r.body.title || r.status}: ${r.body.detail || ""}`;
  await refreshAll();
}

// ---- charts (SVG, drawn here: no chart library) -----------------------------------------------

function niceStep(maxValue, target = 10) {
  const raw = Math.max(maxValue, 1e-3) / target;
  const exp = Math.floor(Math.log10(raw));
  for (const m of [1, 2, 5, 10]) if (m * 10 ** exp >= raw) return m * 10 ** exp;
  return 10 ** (exp + 1);
}

// counts (whole = true) tick in whole numbers: a histogram of 20 spheres once read "15.0"
function axisY(g, x0, y0, h, yMax, unit, whole = false) {
  const step = whole ? Math.max(1, Math.round(niceStep(yMax, 4))) : niceStep(yMax, 4);
  for (let v = 0; v <= yMax + 1e-12; v += step) {
    const y = y0 - (v / yMax) * h;
    g.append(svg("line", { x1: x0 - 3, x2: x0, y1: y, y2: y, stroke: "#888" }));
    g.append(svg("text", { x: x0 - 5, y: y + 3, "text-anchor": "end", class: "ytick" },
      v.toFixed(whole ? 0 : step < 0.01 ? 3 : step < 0.1 ? 2 : 1)));
  }
  g.append(svg("line", { x1: x0, x2: x0, y1: y0, y2: y0 - h, stroke: "#888" }));
}

function barChart(items, opts) {
  const W = 720, H = 200, L = 44, B = 54, T = 14;
  const root = svg("svg", { viewBox: `0 0 ${W} ${H}`, role: "img", "aria-label": opts.title });
  if (!items.length) { root.append(svg("text", { x: L, y: 30 }, "no data")); return root; }
  const second = opts.second || [];
  const yMax = Math.max(...items.map((i) => i.value), ...second.filter((v) => v != null), 1e-6) * 1.1;
  const h = H - B - T, bw = (W - L - 8) / items.length;
  axisY(root, L, H - B, h, yMax, opts.unit);
  root.append(svg("text", { x: 4, y: 10 }, opts.title));
  items.forEach((it, i) => {
    const x = L + i * bw, y = H - B - (it.value / yMax) * h;
    const bar = svg("rect", { x: x + 1, y, width: Math.max(bw - 2, 1), height: H - B - y,
      fill: it.cls === "bad" ? "#c0392b" : "#4a7ab5" });
    bar.append(svg("title", {}, `${it.label}: ${fmt(it.value)} ${opts.unit}`));
    root.append(bar);
    const s = second[i];
    if (s != null) {
      const ys = H - B - (s / yMax) * h;
      root.append(svg("line", { x1: x + 1, x2: x + bw - 1, y1: ys, y2: ys, stroke: "#e67e22", "stroke-width": 3 }));
    }
    root.append(svg("text", { x: x + bw / 2, y: H - B + 8, transform: `rotate(60 ${x + bw / 2} ${H - B + 8})` }, it.label));
  });
  if (second.length) {
    root.append(svg("line", { x1: W - 200, x2: W - 185, y1: 8, y2: 8, stroke: "#e67e22", "stroke-width": 3 }));
    root.append(svg("text", { x: W - 180, y: 11 }, opts.secondLabel));
  }
  return root;
}

function histogram(errors, gate, passed) {
  const W = 720, H = 220, L = 44, B = 34, T = 22;
  const root = svg("svg", { viewBox: `0 0 ${W} ${H}`, role: "img", "aria-label": "histogram of sphere errors" });
  const maxErr = errors.length ? Math.max(...errors) : 0;
  const width = niceStep(maxErr);
  const xMax = Math.max(maxErr, gate || 0, width) * 1.1;
  const nBins = Math.max(1, Math.ceil(maxErr / width + 1e-9));
  const counts = new Array(nBins).fill(0);
  for (const e of errors) counts[Math.min(nBins - 1, Math.floor(e / width))] += 1;
  const yMax = Math.max(...counts, 1);
  const w = W - L - 10, h = H - B - T;
  const X = (v) => L + (v / xMax) * w;
  axisY(root, L, H - B, h, yMax, "", true);
  counts.forEach((c, i) => {
    const y = H - B - (c / yMax) * h;
    const r = svg("rect", { x: X(i * width), y, width: Math.max(X((i + 1) * width) - X(i * width) - 1, 1), height: H - B - y,
      fill: "#4a7ab5", stroke: "#1b1f23", "stroke-width": 0.5 });
    r.append(svg("title", {}, `${fmt(i * width, 3)}–${fmt((i + 1) * width, 3)} mm: ${c} spheres`));
    root.append(r);
  });
  const xs = niceStep(xMax, 6);
  for (let v = 0; v <= xMax + 1e-12; v += xs) {
    root.append(svg("line", { x1: X(v), x2: X(v), y1: H - B, y2: H - B + 3, stroke: "#888" }));
    root.append(svg("text", { x: X(v), y: H - B + 13, "text-anchor": "middle" }, v.toFixed(xs < 0.1 ? 2 : 1)));
  }
  root.append(svg("line", { x1: L, x2: W - 10, y1: H - B, y2: H - B, stroke: "#888" }));
  root.append(svg("text", { x: (L + W) / 2, y: H - 4, "text-anchor": "middle" }, "position error (mm)"));
  root.append(svg("text", { x: 4, y: 12 }, "spheres"));
  if (gate != null) {
    const color = passed ? "#1e8449" : "#c0392b";
    root.append(svg("line", { x1: X(gate), x2: X(gate), y1: T - 6, y2: H - B, stroke: color, "stroke-width": 2,
      "stroke-dasharray": "6 3", "data-gate": gate, class: "gate" }));
    root.append(svg("text", { x: X(gate) - 4, y: T + 4, "text-anchor": "end", fill: color },
      `gate ${fmt(gate, 3)} mm — ${passed ? "PASS" : "FAIL"}`));
  }
  return root;
}

// ---- start --------------------------------------------------------------------------------------

document.addEventListener("DOMContentLoaded", () => {
  $("sign-in-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    signIn($("token").value.trim()).catch(showFailure);
  });
  $("sign-out").addEventListener("click", () => signOut("Signed out."));
  $("ver-prev").addEventListener("click", () => { state.verOffset = Math.max(0, state.verOffset - VER_PAGE); scheduleRefresh(); });
  $("ver-next").addEventListener("click", () => { state.verOffset += VER_PAGE; scheduleRefresh(); });
  $("cal-activate").addEventListener("click", () => activateSelected().catch(showFailure));
  const token = tokenFromFragment() || sessionStorage.getItem(TOKEN_KEY);
  if (token) signIn(token).catch(showFailure); else signOut("");
});
