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
  const SWEEP_POINTS = 121;
  const DEFAULT_START_DEG = 10;
  const DEFAULT_GOAL_DEG = 30;

  const $ = (id) => document.getElementById(id);
  const state = {
    run: 0,             // id of the latest Plan press; answers of older presses are ignored
    planRequest: null,  // the last plan request sent (radians)
    figureBodies: {},   // figure kind -> request body used for it
    urls: [],           // object URLs to revoke on the next run
  };

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

  async function postFigure(kind, body, format) {
    const mime = format === "svg" ? "image/svg+xml" : "image/png";
    const resp = await call(`v1/figures/${kind}?format=${format}`, {
      method: "POST",
      headers: apiHeaders({ "Content-Type": "application/json", "Accept": mime }),
      body: JSON.stringify(body),
    });
    return resp.blob();
  }

  /** A readable sentence for any failure (the problem document's detail when there is one). */
  function describe(err) {
    if (err instanceof ApiError) {
      const p = err.problem;
      let msg = p ? `${p.title || "Error"} (${err.status}): ${p.detail || ""}` : `Error ${err.message}`;
      if (p && p.field) msg += ` [field: ${p.field}]`;
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
    if (req.objective === "weighted") {
      req.weights = {};
      for (const k of ["d_a", "sensitivity", "energy", "t_p"]) {
        req.weights[k] = readNumber(`w-${k}`, `Weight of ${k}`);
      }
    }
    return req;
  }

  /** A sweep over the plan's feasible dphi range (padded), else around the planned dphi. */
  function sweepRequest(req, plan) {
    const iv = plan.feasible_phi_changes || [];
    let lo, hi;
    if (iv.length) {
      lo = Math.min(...iv.map((p) => p[0]));
      hi = Math.max(...iv.map((p) => p[1]));
      const pad = Math.max(0.25 * (hi - lo), 0.5 * DEG);
      lo -= pad;
      hi += pad;
    } else {
      lo = plan.phi_change - 20 * DEG;
      hi = plan.phi_change + 20 * DEG;
    }
    const lim = 4 * Math.PI - 1e-9;
    lo = Math.max(lo, -lim);
    hi = Math.min(hi, lim);
    return Object.assign({}, req, { phi_change_range: [lo, hi], points: SWEEP_POINTS });
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
    for (const kind of FIGURES) {
      const img = $(`fig-${kind}`);
      img.removeAttribute("src");
      img.closest("figure").classList.remove("loaded", "failed");
      $(`fig-status-${kind}`).textContent = "";
    }
  }

  function showPlan(plan, text) {
    $("placeholder").hidden = true;
    $("plan-out").hidden = false;
    $("out-method").textContent = plan.method;
    $("out-dphi").textContent = `${fmtDeg(plan.phi_change, 2)} deg`;
    $("out-duration").textContent = `${fmtNum(plan.duration, 3)} s`;
    const ind = plan.indicators || {};
    $("ind-d_a").textContent = fmtDeg(ind.d_a, 2);
    $("ind-t_p").textContent = ind.t_p === null || ind.t_p === undefined ? "n/a" : String(ind.t_p);
    $("ind-sensitivity").textContent = fmtNum(ind.sensitivity, 3);
    $("ind-margin").textContent = fmtDeg(ind.margin, 2);
    $("ind-terminal_error").textContent = fmtExp((plan.validation || {}).terminal_error);

    const list = $("feasible");
    const items = (plan.feasible_phi_changes || []).map((p) => {
      const li = document.createElement("li");
      li.textContent = `${fmtDeg(p[0], 2)} .. ${fmtDeg(p[1], 2)} deg`;
      if (plan.phi_change >= p[0] - 1e-12 && plan.phi_change <= p[1] + 1e-12) {
        li.classList.add("chosen");
        li.title = "contains the planned dphi";
      }
      return li;
    });
    if (!items.length) {
      const li = document.createElement("li");
      li.className = "muted";
      li.textContent = "none reported (not searched by this method)";
      items.push(li);
    }
    list.replaceChildren(...items);

    const url = URL.createObjectURL(new Blob([text], { type: "application/json" }));
    state.urls.push(url);
    const link = $("download-json");
    link.href = url;
    link.download = `plan-${plan.method}.json`;
  }

  async function showFigure(run, kind, body) {
    const status = $(`fig-status-${kind}`);
    const img = $(`fig-${kind}`);
    const figure = img.closest("figure");
    status.textContent = "rendering…";
    try {
      const blob = await postFigure(kind, body, "png");
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
    state.figureBodies = { joint_angles: req, chained_state: req, sweep: sweepRequest(req, plan) };
    setStatus("Rendering figures…", true);
    await Promise.all(FIGURES.map((k) => showFigure(run, k, state.figureBodies[k])));
    if (run === state.run) setStatus(`Planned in ${fmtNum((plan.timing || {}).total, 2)} s.`, false);
  }

  async function downloadSVG(kind) {
    const body = state.figureBodies[kind];
    if (!body) return;
    const status = $(`fig-status-${kind}`);
    status.textContent = "rendering SVG…";
    try {
      const blob = await postFigure(kind, body, "svg");
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
    $("n").addEventListener("change", loadDefaults);
    $("objective").addEventListener("change", syncWeights);
    $("api-key").addEventListener("change", () => {
      if ($("plan-form").dataset.defaults === "failed") loadDefaults();  // now with the key
    });
    document.querySelectorAll("button[data-svg]").forEach((b) =>
      b.addEventListener("click", () => downloadSVG(b.dataset.svg)));
    syncWeights();
    loadDefaults();
  });
})();
