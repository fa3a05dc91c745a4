/* Plan explorer: a form over the planning service's own API (no framework, no build step).
 *
 * Degrees in the form, radians on the wire: every angle typed here is multiplied by pi/180
 * before it is sent, and every angle shown is converted back. All URLs are relative to the
 * page, so the page also works behind a proxy that mounts the service under a prefix.
 */
"use strict";

(function () {
  const DEG = Math.PI / 180;
  const FIGURES = ["joint_angles", "chained_state", "sweep"];
  // The sweep figure: at least SWEEP_MIN_POINTS, and at least SWEEP_PER_WINDOW across the
  // narrowest feasible window, within the service's default limit of sweep points.
  const SWEEP_MIN_POINTS = 201;
  const SWEEP_MAX_POINTS = 2001;
  const SWEEP_PER_WINDOW = 40;
  const DEFAULT_START_DEG = 10;
  const DEFAULT_GOAL_DEG = 30;

  const $ = (id) => document.getElementById(id);
  const state = {
    run: 0,             // id of the latest Plan press; answers of older presses are ignored
    planRequest: null,  // the last plan request sent (radians)
    figures: {},        // figure kind -> {path, body}: the answer it is drawn from
    urls: [],           // object URLs to revoke on the next run
  };
  // whether a pointer (mouse button, finger) is down now: see the API key's change handler
  let pointerHeld = false;
  document.addEventListener("pointerdown", () => { pointerHeld = true; }, true);
  document.addEventListener("pointerup", () => { pointerHeld = false; }, true);
  document.addEventListener("pointercancel", () => { pointerHeld = false; }, true);
  /** Run ``fn`` once the pointer held now is released (after the click that release
   *  dispatches) or its press cancelled. */
  function afterPress(fn) {
    const go = () => {
      document.removeEventListener("pointerup", go, true);
      document.removeEventListener("pointercancel", go, true);
      setTimeout(fn, 0);
    };
    document.addEventListener("pointerup", go, true);
    document.addEventListener("pointercancel", go, true);
  }

  // ------------------------------------------------------------------ API calls
  class ApiError extends Error {
    constructor(status, problem, fallback) {
      super((problem && problem.detail) || fallback || "request failed");
      this.status = status;
      this.problem = problem;
    }
  }

  function apiHeaders(extra) {
    const h = Object.assign({}, extra || {});
    const key = $("api-key").value.trim();
    if (key) h["X-API-Key"] = key;
    return h;
  }

  async function failure(resp) {
    let problem = null;
    const text = await resp.text().catch(() => "");
    try { problem = JSON.parse(text); } catch (e) { problem = null; }
    if (!problem || typeof problem !== "object") problem = null;
    return new ApiError(resp.status, problem, `${resp.status} ${resp.statusText || ""}`.trim());
  }

  async function call(path, options) {
    let resp;
    try {
      resp = await fetch(path, options);
    } catch (e) {
      throw new Error(`The service could not be reached (${e.message}).`);
    }
    if (!resp.ok) throw await failure(resp);
    return resp;
  }

  async function postJSON(path, body) {
    const resp = await call(path, {
      method: "POST",
      headers: apiHeaders({ "Content-Type": "application/json", "Accept": "application/json" }),
      body: JSON.stringify(body),
    });
    const text = await resp.text();
    return { text: text, data: JSON.parse(text) };
  }

  async function postFigure(path, body, format) {
    const mime = format === "svg" ? "image/svg+xml" : "image/png";
    const resp = await call(`${path}?format=${format}`, {
      method: "POST",
      headers: apiHeaders({ "Content-Type": "application/json", "Accept": mime }),
      body: JSON.stringify(body),
    });
    return resp.blob();
  }

  /** The service's words in the page's terms: joints th1..thn for start[i]/goal[i], and
   *  degrees for angles (the page takes degrees and sends radians). */
  function pageTerms(text) {
    const deg = (rad) => `${(Number(rad) / DEG).toFixed(2)}°`;
    return String(text)
      .replace(/\b(start|goal)\[(\d+)\]/g, (m, which, i) => `${which} of th${Number(i) + 1}`)
      .replace(/-?\d[\d.e+-]* rad \((-?[\d.]+) deg\)/g, "$1°")
      .replace(/\(0, pi\/2\) rad = \(0, 90\) deg/g, "the open range 0°..90°")
      .replace(/\[-2 pi, 2 pi\] rad = \[-360, 360\] deg/g, "-360°..360°")
      .replace(/\((-?\d[\d.e+-]*), (-?\d[\d.e+-]*)\) rad/g, (m, a, b) => `(${deg(a)}, ${deg(b)})`)
      .replace(/; angles are in radians/g, "");
  }

  /** A readable sentence for any failure (the problem document's detail when there is one). */
  function describe(err) {
    if (err instanceof ApiError) {
      const p = err.problem;
      let msg = p ? `${p.title || "Error"} (${err.status}): ${pageTerms(p.detail || "")}` : `Error ${err.message}`;
      if (p && p.field) msg += ` [field: ${pageTerms(p.field)}]`;
      if (err.status === 401) {
        msg += " Enter a valid key in the API key field (Access) and try again.";
      } else if (err.status === 503) {
        msg += " The service is busy; try again in a moment.";
      }
      return msg;
    }
    return err && err.message ? err.message : String(err);
  }

  // ------------------------------------------------------------------ form
  function jointRow(i, start, goal, gain, exponent) {
    const tr = document.createElement("tr");
    const th = document.createElement("th");
    th.scope = "row";
    th.textContent = `th${i}`;
    tr.appendChild(th);
    const cell = (input) => { const td = document.createElement("td"); td.appendChild(input); tr.appendChild(td); };
    const num = (id, value, attrs) => {
      const el = document.createElement("input");
      el.type = "number";
      el.id = id;
      el.step = "any";
      el.required = true;
      el.value = value;
      Object.assign(el, attrs || {});
      return el;
    };
    cell(num(`start-${i}`, start, { title: `start of joint ${i} (deg)` }));
    cell(num(`goal-${i}`, goal, { title: `goal of joint ${i} (deg)` }));
    if (i === 1) {
      for (let k = 0; k < 2; k++) {
        const td = document.createElement("td");
        td.className = "muted center";
        td.textContent = "driven";
        td.title = "joint 1 is driven directly by the second motor (u2)";
        tr.appendChild(td);
      }
    } else {
      cell(num(`gain-${i}`, gain, { min: "0", title: `gain K${i}` }));
      cell(num(`exponent-${i}`, exponent, { min: "1", max: "12", step: "1", title: `exponent m${i}` }));
    }
    return tr;
  }

  function currentN() {
    const n = parseInt($("n").value, 10);
    return Number.isFinite(n) ? Math.min(8, Math.max(3, n)) : 3;
  }

  /** Make the joint table have n rows: rows are added or removed at the end, never rebuilt,
   *  so that typing in a row is never interrupted. */
  function setJointCount(n) {
    const body = $("joint-rows");
    while (body.rows.length > n) body.deleteRow(body.rows.length - 1);
    for (let i = body.rows.length + 1; i <= n; i++) {
      body.appendChild(jointRow(i, DEFAULT_START_DEG, DEFAULT_GOAL_DEG, "", ""));
    }
  }

  /** Put a robot's constants into the gain and exponent fields (in place). */
  function applyRobot(robot) {
    for (let i = 2; i <= robot.gains.length + 1; i++) {
      const g = $(`gain-${i}`), m = $(`exponent-${i}`);
      if (g) g.value = robot.gains[i - 2];
      if (m) m.value = robot.exponents[i - 2];
    }
  }

  async function loadDefaults() {
    const n = currentN();
    if ($("n").value !== String(n)) $("n").value = n;
    setJointCount(n);
    const note = $("robot-note");
    try {
      const resp = await call(`v1/robots/default?n=${n}`, { headers: apiHeaders({ "Accept": "application/json" }) });
      const robot = await resp.json();
      if (currentN() !== n) return;  // n changed meanwhile
      applyRobot(robot);
      note.hidden = !robot.note;
      note.textContent = robot.note || "";
      $("plan-form").dataset.defaults = "loaded";
    } catch (err) {
      note.hidden = false;
      note.textContent = "Could not load the default constants: " + describe(err);
      $("plan-form").dataset.defaults = "failed";
    }
  }

  function readNumber(id, what) {
    const el = $(id);
    const text = el.value.trim();
    const x = Number(text);
    if (text === "" || !Number.isFinite(x)) {
      throw new Error(`${what} must be a number.`);
    }
    return x;
  }

  /** The plan request of the form (angles converted from degrees to radians). */
  function buildRequest() {
    const n = currentN();
    const start = [], goal = [], gains = [], exponents = [];
    for (let i = 1; i <= n; i++) {
      start.push(readNumber(`start-${i}`, `Start angle of joint ${i}`) * DEG);
      goal.push(readNumber(`goal-${i}`, `Goal angle of joint ${i}`) * DEG);
      if (i > 1) {
        const g = $(`gain-${i}`).value.trim(), m = $(`exponent-${i}`).value.trim();
        if (g !== "" || m !== "") {
          gains.push(readNumber(`gain-${i}`, `Gain K${i}`));
          const e = readNumber(`exponent-${i}`, `Exponent m${i}`);
          if (!Number.isInteger(e)) throw new Error(`Exponent m${i} must be an integer.`);
          exponents.push(e);
        }
      }
    }
    const req = {
      start: start,
      goal: goal,
      method: $("method").value,
      objective: $("objective").value,
      singularity: $("singularity").value,
    };
    if (gains.length) {
      if (gains.length !== n - 1) throw new Error("Give all gains and exponents, or none (default robot).");
      req.robot = { gains: gains, exponents: exponents };
    } else {
      req.robot = {};  // the default robot of n joints: the service wants it said for n != 3
    }
    if ($("duration").value.trim() !== "") req.duration = readNumber("duration", "Duration T");
    // optional limits of both actuators' rates and their derivatives (the figures draw the
    // rates against them; a duration too short for them is answered with the shortest one)
    if ($("max-u").value.trim() !== "") {
      req.max_u1 = req.max_u2 = readNumber("max-u", "Rate limit");
    }
    if ($("max-du").value.trim() !== "") {
      req.max_du1 = req.max_du2 = readNumber("max-du", "Rate change limit");
    }
    if ($("max-reversals").value.trim() !== "") {
      const k = readNumber("max-reversals", "Max reversals");
      if (!Number.isInteger(k) || k < 0) throw new Error("Max reversals must be a whole number >= 0.");
      req.max_reversals = k;
    }
    if ($("pareto").checked) req.pareto = true;
    if (req.objective === "weighted") {
      req.weights = {};
      for (const k of ["d_a", "sensitivity", "energy", "t_p"]) {
        req.weights[k] = readNumber(`w-${k}`, `Weight of ${k}`);
      }
    }
    return req;
  }

  /** The dphi range and number of points of the sweep figure: around the feasible windows,
   *  fine enough that SWEEP_PER_WINDOW points fall into the narrowest of them. When the windows
   *  lie too far apart for that, the window of the planned dphi alone (or the nearest one). */
  function sweepSpan(phi, windows) {
    if (!windows.length) return { lo: phi - 20 * DEG, hi: phi + 20 * DEG, points: SWEEP_MIN_POINTS };
    const span = (ws) => {
      const lo = Math.min(...ws.map((w) => w[0])), hi = Math.max(...ws.map((w) => w[1]));
      const narrowest = Math.max(Math.min(...ws.map((w) => w[1] - w[0])), 1e-7);
      const pad = Math.max(0.25 * (hi - lo), 0.5 * narrowest, 0.01 * DEG);
      const points = Math.ceil((hi - lo + 2 * pad) / (narrowest / SWEEP_PER_WINDOW)) + 1;
      return { lo: lo - pad, hi: hi + pad, points: Math.max(points, SWEEP_MIN_POINTS) };
    };
    let s = span(windows);
    if (s.points > SWEEP_MAX_POINTS) {
      const dist = (w) => Math.max(w[0] - phi, phi - w[1], 0);
      const own = windows.reduce((a, b) => (dist(b) < dist(a) ? b : a));
      s = span([own]);
    }
    const lim = 4 * Math.PI - 1e-9;
    return { lo: Math.max(s.lo, -lim), hi: Math.min(s.hi, lim), points: Math.min(s.points, SWEEP_MAX_POINTS) };
  }

  /** The sweep answer for the figure: over the plan's feasible windows; a plan that reports
   *  none (its method did not search them) gets them from a coarse sweep first. */
  async function sweepFor(run, req, plan) {
    // the sweep figure ranks its grid by the paper's rule (fewest t_p, then smallest d_a):
    // its requests ask for that objective, whatever the plan's (the default objective's
    // search over 721 points took longer than the time limit)
    req = Object.assign({}, req, { objective: "tp_then_da" });
    delete req.weights;
    let windows = plan.feasible_phi_changes || [];
    if (!windows.length) {
      const coarse = await postJSON("v1/sweeps", Object.assign({}, req, {
        phi_change_range: [-Math.PI, Math.PI], points: 721, intervals: true }));
      windows = coarse.data.feasible_phi_changes || [];
      if (run === state.run) showWindows(windows, plan, " (from a sweep; this method does not search them)");
    }
    const s = sweepSpan(plan.phi_change, windows);
    const answer = await postJSON("v1/sweeps", Object.assign({}, req, {
      phi_change_range: [s.lo, s.hi], points: s.points, intervals: true }));
    return answer.data;
  }

  /** The grid's best member by the figure's rule (fewest t_p, then smallest d_a), or -1. */
  function bestOnGrid(sweep) {
    let best = -1;
    sweep.phi_change.forEach((x, i) => {
      const tp = sweep.t_p[i], da = sweep.d_a[i];
      if (tp === null || da === null) return;
      if (best < 0 || tp < sweep.t_p[best] || (tp === sweep.t_p[best] && da < sweep.d_a[best])) best = i;
    });
    return best;
  }

  function showSweepNote(sweep, plan) {
    const xs = sweep.phi_change, n = xs.length;
    const step = n > 1 ? (xs[n - 1] - xs[0]) / (n - 1) : 0;
    const best = bestOnGrid(sweep);
    $("sweep-range").textContent = `${fmtDeg(xs[0], 2)} .. ${fmtDeg(xs[n - 1], 2)} deg, ${n} points (step ${fmtDeg(step, 4)} deg)`;
    $("sweep-best").textContent = best < 0 ? "none" : `${fmtDeg(xs[best], 3)} deg (t_p = ${sweep.t_p[best]})`;
    $("sweep-planned").textContent = `${fmtDeg(plan.phi_change, 3)} deg`;
    $("sweep-note").hidden = false;
  }

  // ------------------------------------------------------------------ output
  const fmtDeg = (rad, digits) => (rad === null || rad === undefined) ? "n/a" : (rad / DEG).toFixed(digits);
  const fmtNum = (x, digits) => (x === null || x === undefined) ? "n/a" : Number(x).toFixed(digits);
  const fmtExp = (x) => (x === null || x === undefined) ? "n/a" : Number(x).toExponential(2);

  function setStatus(text, busy) {
    $("status").textContent = text;
    $("plan-button").disabled = !!busy;
    document.body.classList.toggle("busy", !!busy);
  }

  function showError(message) {
    const box = $("error");
    box.textContent = message;
    box.hidden = !message;
  }

  /** Bring the results into view when they start outside the window (long form, narrow layout). */
  function reveal() {
    const box = $("results").getBoundingClientRect();
    if (box.top < 0 || box.top > window.innerHeight - 80) {
      $("results").scrollIntoView({ block: "start", behavior: "smooth" });
    }
  }

  function resetOutput() {
    showError("");
    for (const url of state.urls) URL.revokeObjectURL(url);
    state.urls = [];
    $("plan-out").hidden = true;
    $("sweep-note").hidden = true;
    state.figures = {};
    $("front-out").hidden = true;
    for (const kind of FIGURES.concat(["pareto"])) {
      const img = $(`fig-${kind}`);
      img.removeAttribute("src");
      img.closest("figure").classList.remove("loaded", "failed");
      $(`fig-status-${kind}`).textContent = "";
    }
  }

  /** The feasible dphi windows; ``source`` says where they come from when not from the plan. */
  function showWindows(windows, plan, source) {
    const items = windows.map((p) => {
      const li = document.createElement("li");
      li.textContent = `${fmtDeg(p[0], 2)} .. ${fmtDeg(p[1], 2)} deg${source}`;
      if (plan.phi_change >= p[0] - 1e-12 && plan.phi_change <= p[1] + 1e-12) {
        li.classList.add("chosen");
        li.title = "contains the planned dphi";
      }
      return li;
    });
    if (!items.length) {
      const li = document.createElement("li");
      li.className = "muted";
      li.textContent = source ? "none: no member of the polynomial family is singularity-free"
        : "none reported (not searched by this method)";
      items.push(li);
    }
    $("feasible").replaceChildren(...items);
  }

  function showPlan(plan, text) {
    $("placeholder").hidden = true;
    $("plan-out").hidden = false;
    $("out-method").textContent = plan.method;
    $("out-dphi").textContent = `${fmtDeg(plan.phi_change, 2)} deg`;
    $("out-duration").textContent = `${fmtNum(plan.duration, 3)} s`;
    const ind = plan.indicators || {};
    // the paper's indicators of the exact plan on its own schedule (plan_indicators; the
    // handed-out path's, run along its time law, are in indicators)
    const paper = plan.plan_indicators || ind;
    $("ind-d_a").textContent = fmtDeg(paper.d_a, 2);
    $("ind-t_p").textContent = paper.t_p === null || paper.t_p === undefined ? "n/a" : String(paper.t_p);
    $("ind-sensitivity").textContent = fmtNum(paper.sensitivity, 3);
    $("ind-margin").textContent = fmtDeg(ind.margin, 2);
    $("ind-terminal_error").textContent = fmtExp((plan.validation || {}).terminal_error);

    showWindows(plan.feasible_phi_changes || [], plan, "");

    const url = URL.createObjectURL(new Blob([text], { type: "application/json" }));
    state.urls.push(url);
    const link = $("download-json");
    link.href = url;
    link.download = `plan-${plan.method}.json`;
  }

  /** Draw figure ``kind`` from an answer: ``source`` is a promise of {path, body}. */
  async function showFigure(run, kind, source) {
    const status = $(`fig-status-${kind}`);
    const img = $(`fig-${kind}`);
    const figure = img.closest("figure");
    status.textContent = "rendering…";
    try {
      const fig = await source;
      if (run !== state.run) return;
      state.figures[kind] = fig;
      const blob = await postFigure(fig.path, fig.body, "png");
      if (run !== state.run) return;
      const url = URL.createObjectURL(blob);
      state.urls.push(url);
      await new Promise((resolve, reject) => {
        img.onload = resolve;
        img.onerror = () => reject(new Error("the image could not be decoded"));
        img.src = url;
      });
      figure.classList.add("loaded");
      status.textContent = "";
    } catch (err) {
      if (run !== state.run) return;
      figure.classList.add("failed");
      status.textContent = "failed: " + describe(err);
    }
  }

  async function onPlan(event) {
    event.preventDefault();
    const run = ++state.run;
    resetOutput();
    let req;
    try {
      req = buildRequest();
    } catch (err) {
      showError(err.message);
      $("placeholder").hidden = true;
      setStatus("Not sent: see the message.", false);
      reveal();
      return;
    }
    $("request-preview").textContent = JSON.stringify(req, null, 2);
    setStatus("Planning…", true);
    let answer;
    try {
      answer = await postJSON("v1/plans", req);
    } catch (err) {
      if (run !== state.run) return;
      setStatus("Failed: see the message.", false);
      $("placeholder").hidden = true;
      showError(describe(err));
      reveal();
      return;
    }
    if (run !== state.run) return;
    const plan = answer.data;
    state.planRequest = req;
    showPlan(plan, answer.text);
    reveal();
    // every figure is drawn from an answer the page has: the plan's, and a sweep's
    const sweep = sweepFor(run, req, plan).then((data) => {
      if (run === state.run) showSweepNote(data, plan);
      return { path: "v1/figures/from_sweep", body: { sweep: data, planned_phi_change: plan.phi_change } };
    });
    const sources = {
      joint_angles: Promise.resolve({ path: "v1/figures/from_plan/joint_angles", body: plan }),
      chained_state: Promise.resolve({ path: "v1/figures/from_plan/chained_state", body: plan }),
      sweep: sweep,
    };
    setStatus("Rendering figures…", true);
    await Promise.all(FIGURES.map((k) => showFigure(run, k, sources[k])).concat([showFront(run, plan)]));
    if (run === state.run) setStatus(`Planned in ${fmtNum((plan.timing || {}).total, 2)} s.`, false);
  }

  /** A front member as a plan answer the figure routes take (the main plan's robot). */
  function memberAsPlan(member, plan) {
    const out = Object.assign({}, member, {
      status: "success", robot: plan.robot, feasible_phi_changes: [], timing: {}, diagnostics: {},
    });
    for (const k of ["origin", "max_reversals", "chosen"]) delete out[k];
    return out;
  }

  /** The trade-off of a pareto answer: a row per member (Show draws it) and its figure. */
  function showFront(run, plan) {
    const members = plan.pareto || [];
    $("front-out").hidden = members.length === 0;
    const body = $("front-rows");
    body.textContent = "";
    if (!members.length) return Promise.resolve();
    members.forEach((m) => {
      const row = document.createElement("tr");
      const ind = m.indicators || {};
      for (const text of [String(m.max_reversals), fmtDeg(ind.deviation, 3), fmtNum(ind.energy, 3)]) {
        const cell = document.createElement("td");
        cell.textContent = text;
        row.appendChild(cell);
      }
      const cell = document.createElement("td");
      const button = document.createElement("button");
      button.type = "button";
      button.className = "link";
      button.textContent = m.chosen ? "show (main plan)" : "show";
      button.addEventListener("click", () => pickMember(m, plan));
      cell.appendChild(button);
      row.appendChild(cell);
      body.appendChild(row);
    });
    return showFigure(run, "pareto", Promise.resolve({ path: "v1/figures/from_plan/pareto", body: plan }));
  }

  /** Show one member of the front: its numbers and its time figures. */
  async function pickMember(member, plan) {
    const run = ++state.run;
    const shown = memberAsPlan(member, plan);
    showPlan(shown, JSON.stringify(shown, null, 2));
    setStatus(`Showing the plan with ${member.max_reversals} reversals (max_reversals = ${member.max_reversals} asks for it alone).`, true);
    await Promise.all(["joint_angles", "chained_state"].map((k) =>
      showFigure(run, k, Promise.resolve({ path: `v1/figures/from_plan/${k}`, body: shown }))));
    if (run === state.run) setStatus(`Showing the plan with ${member.max_reversals} reversals.`, false);
  }

  async function downloadSVG(kind) {
    const fig = state.figures[kind];
    if (!fig) return;
    const status = $(`fig-status-${kind}`);
    status.textContent = "rendering SVG…";
    try {
      const blob = await postFigure(fig.path, fig.body, "svg");
      const url = URL.createObjectURL(blob);
      const a = document.createElement("a");
      a.href = url;
      a.download = `${kind}.svg`;
      document.body.appendChild(a);
      a.click();
      a.remove();
      setTimeout(() => URL.revokeObjectURL(url), 10000);
      status.textContent = "";
    } catch (err) {
      status.textContent = "SVG failed: " + describe(err);
    }
  }

  function syncWeights() {
    $("weights").hidden = $("objective").value !== "weighted";
  }

  document.addEventListener("DOMContentLoaded", () => {
    setJointCount(3);
    applyRobot({ gains: [0.88658, 0.7115], exponents: [2, 3] });  // until the service answers
    $("plan-form").addEventListener("submit", onPlan);
    $("load-defaults").addEventListener("click", loadDefaults);
    $("n").addEventListener("change", () => {
      // another robot: the result on screen is not its plan (a plan still on its way is
      // dropped too)
      state.run++;
      resetOutput();
      setStatus("", false);
      loadDefaults();
    });
    $("objective").addEventListener("change", syncWeights);
    $("api-key").addEventListener("change", () => {
      if ($("plan-form").dataset.defaults !== "failed") return;
      // now with the key. The change fires when a press elsewhere (Plan, say) takes the
      // focus: the defaults' answer replaces the note above the button within milliseconds,
      // which would move the button from under a pointer still held down and lose the
      // click. So the reload starts once the press is over and its click dispatched.
      if (pointerHeld) afterPress(loadDefaults); else loadDefaults();
    });
    document.querySelectorAll("button[data-svg]").forEach((b) =>
      b.addEventListener("click", () => downloadSVG(b.dataset.svg)));
    syncWeights();
    loadDefaults();
  });
})();
