// Lesion marks in the viewer: numbered markers with labels on the body, the list by body region
// (the server's analysis/body_regions.py), the earlier scan's marks carried here, and every refusal
// or failure said on the page (never only in the console).
import * as THREE from "three";
import { getJSON, send, el, fmt, ending } from "/static/common.js";

const OWN = 0xe040fb;
const CARRIED = 0xffd600;
const LABEL_OFF_MM = 18;  // a label floats this far off the skin, away from the body's axis

// A round label with the mark's number, drawn on a canvas; constant size on the screen, hidden by
// the body when it stands behind it.
function label(text, colour) {
  const canvas = document.createElement("canvas");
  canvas.width = canvas.height = 64;
  const g = canvas.getContext("2d");
  g.fillStyle = `#${colour.toString(16).padStart(6, "0")}`;
  g.beginPath(); g.arc(32, 32, 30, 0, 2 * Math.PI); g.fill();
  g.fillStyle = "#111"; g.font = `bold ${text.length > 2 ? 24 : 32}px sans-serif`;
  g.textAlign = "center"; g.textBaseline = "middle"; g.fillText(text, 32, 34);
  const sprite = new THREE.Sprite(new THREE.SpriteMaterial({ map: new THREE.CanvasTexture(canvas), sizeAttenuation: false }));
  sprite.scale.set(0.035, 0.035, 1);
  sprite.center.set(-0.1, -0.1);  // up and to the right of its place: the marker stays in sight
  return sprite;
}

// Where a mark's label goes: off the skin, away from the body's vertical axis.
function labelPlace(point, body) {
  const out = body ? [point[0] - body.centre_xy[0], point[1] - body.centre_xy[1]] : [0, 0];
  const n = Math.hypot(out[0], out[1]) || 1;
  return [point[0] + (LABEL_OFF_MM * out[0]) / n, point[1] + (LABEL_OFF_MM * out[1]) / n, point[2]];
}

export class MarksPane {
  // api: this scan's API root; group: the scene's group for markers; view: { selectSpot(point),
  // point() (the selected spot), redraw() }; hooks: the viewer's test hooks.
  constructor(api, group, view, hooks) {
    Object.assign(this, { api, group, view, hooks, data: null });
    hooks.marks = { labels: [], errors: [] };
  }

  error(text) {
    this.hooks.marks.errors.push(text);
    const box = document.getElementById("marks-error");
    if (box) box.textContent = text;
    else document.getElementById("marks").prepend(el("p", { class: "error", id: "marks-error" }, text));
  }

  // Runs an action of the pane; a refusal or failure is shown above the marks.
  async act(action) {
    const box = document.getElementById("marks-error");
    if (box) box.textContent = "";
    try { await action(); } catch (error) { this.error(String(error.message || error)); }
  }

  async load() {
    this.data = await getJSON(`${this.api}/marks`);
    this.draw();
    await this.render();
  }

  draw() {
    this.group.clear();
    const labels = [];
    const body = this.data?.body;
    for (const [list, colour, prefix] of [[this.data?.marks || [], OWN, ""], [this.data?.carried || [], CARRIED, "E"]]) {
      for (const m of list) {
        const ball = new THREE.Mesh(new THREE.SphereGeometry(6, 16, 12), new THREE.MeshBasicMaterial({ color: colour }));
        ball.position.set(...m.point_mm);
        const text = `${prefix}${m.number}`;
        const tag = label(text, colour);
        tag.position.set(...labelPlace(m.point_mm, body));
        this.group.add(ball, tag);
        labels.push({ text, name: m.name, point_mm: m.point_mm, at: tag.position.toArray() });
      }
    }
    this.hooks.marks.labels = labels;
    this.view.redraw();
  }

  // One row of the list: the number (as on the body), the name, and its buttons.
  row(mark, prefix, note, ...buttons) {
    return el("div", { class: "mark", dataset: { number: `${prefix}${mark.number}` } },
      el("span", {}, el("span", { class: `num ${prefix ? "carried" : "own"}` }, `${prefix}${mark.number}`), " ", el("b", {}, mark.name),
        note ? el("span", { class: "muted" }, `  ${note}`) : null),
      el("span", {}, ...buttons));
  }

  // Why a carried mark is in doubt, in the words of the carrier's two tests (analysis/registration.py).
  doubt(mark) {
    const why = [];
    if (mark.doubt.includes("surface_gap")) why.push(`This scan's surface is ${fmt(mark.surface_gap_mm, 1)} mm from where the body's fit puts this skin (around it, ${fmt(mark.fit_rmse_mm, 1)} mm): it may not hold this spot.`);
    if (mark.doubt.includes("surfaces_apart")) why.push(`Around this spot the two scans' surfaces are ${fmt(mark.surfaces_apart_mm, 1)} mm apart: the skin changed shape between the visits, or a scan missed it, and the fit may not place this spot.`);
    return `${why.join(" ")} Check the images before keeping it.`;
  }

  // Marks grouped by body region, in the server's order of regions.
  byRegion(marks) {
    const order = this.data.regions || [];
    const groups = new Map(order.map((r) => [r, []]));
    for (const m of marks) {
      const key = m.region || "body";
      if (!groups.has(key)) groups.set(key, []);
      groups.get(key).push(m);
    }
    return [...groups].filter(([, list]) => list.length);
  }

  async compare(mark) {
    const { api } = this;
    const at = (p) => new URLSearchParams({ x: p[0], y: p[1], z: p[2], count: 1 });
    const here = await getJSON(`${api}/navigate?${at(mark.point_mm)}`);
    const prevApi = `/api/scans/${encodeURIComponent(this.data.previous_scan)}`;
    const then = await getJSON(`${prevApi}/navigate?${at(mark.from_point_mm)}`);
    const cropOf = (base, v) => v ? el("div", { class: "crop" }, el("img", { src: `${base}/images/${encodeURIComponent(v.file.split("/").pop())}?u=${v.u_px.toFixed(1)}&v=${v.v_px.toFixed(1)}&half=160` }),
      el("div", { class: "hint" }, `${v.camera_id} ${fmt(v.angle_deg, 1)}° · ${fmt(v.resolution_mm_px, 3)} mm/px`)) : el("p", { class: "muted" }, "no image");
    document.getElementById(`pair-${mark.id}`).replaceChildren(el("div", {}, el("b", {}, "Earlier"), cropOf(prevApi, then.views[0])),
      el("div", {}, el("b", {}, "This scan"), cropOf(api, here.views[0])));
  }

  async render() {
    const root = document.getElementById("marks");
    const m = this.data;
    const { api, view } = this;
    const button = (text, action) => el("button", { onclick: () => this.act(action) }, text);
    // Only the same patient's earlier visits: the server offers no other (and refuses any other).
    const { visits, note } = await getJSON(`${api}/earlier`);
    const select = el("select", { id: "previous" }, el("option", { value: "" }, "— none —"));
    for (const s of visits) {
      const ended = ending(s);
      const opt = el("option", { value: s.folder }, `${s.scan_id} · ${(s.created_utc || "").slice(0, 10)}${ended.done ? "" : ` · ${ended.label}`}`);
      if (s.folder === m.previous_scan) opt.selected = true;
      select.append(opt);
    }
    select.addEventListener("change", () => this.act(async () => {
      await send("PUT", `${api}/previous`, { previous_scan: select.value || null });
      await this.load();
    }));
    const name = el("input", { id: "mark-name", placeholder: "name, e.g. naevus left scapula", maxlength: 80, style: "width:100%;padding:7px" });
    const add = el("button", { class: "primary", id: "add-mark", onclick: () => this.act(async () => {
      if (!view.point()) throw new Error("Click the spot on the body first.");
      await send("POST", `${api}/marks`, { name: name.value, point_mm: view.point() });
      await this.load();
    }) }, "Mark the selected spot");
    root.replaceChildren(el("p", { class: "error", id: "marks-error" }), el("h2", {}, "Marks on this scan"));
    for (const [region, list] of this.byRegion(m.marks)) {
      root.append(el("h3", { class: "region" }, region));
      for (const mark of list) {
        root.append(this.row(mark, "", mark.carried_from ? "(carried)" : "",
          button("Show", () => view.selectSpot(mark.point_mm)), " ",
          button("Delete", async () => { await send("DELETE", `${api}/marks/${mark.id}`); await this.load(); })));
      }
    }
    if (!m.marks.length) root.append(el("p", { class: "muted" }, "None yet."));
    root.append(el("div", { style: "margin:10px 0" }, name), add);
    root.append(el("h2", {}, "Compare with an earlier scan of this patient"), note ? el("p", { class: "muted", id: "no-patient" }, note) : select);
    if (m.registration && m.registration.error) root.append(el("p", { class: "error" }, m.registration.error));
    else if (m.registration) root.append(el("p", { class: "muted" }, `Bodies registered: ${fmt(100 * m.registration.fitness, 0)} % overlap, ${fmt(m.registration.rmse_mm, 1)} mm rms.`));
    for (const [region, list] of this.byRegion(m.carried)) {
      root.append(el("h3", { class: "region" }, region));
      for (const mark of list) {
        const doubt = mark.in_doubt ? el("p", { class: "doubt" }, this.doubt(mark)) : null;
        root.append(this.row(mark, "E", mark.placed_by === "pictures"
          ? `from the earlier scan, placed on the pictures (match ${fmt(mark.picture_score, 2)})` : "from the earlier scan, placed by the body's shape",
        button("Compare", () => this.compare(mark)), " ",
        button("Show", () => view.selectSpot(mark.point_mm)), " ",
        button("Keep here", async () => {
          await send("POST", `${api}/marks`, { name: mark.name, point_mm: mark.point_mm, carried_from: { scan: m.previous_scan, mark: mark.id } });
          await this.load();
        })), doubt, el("div", { class: "pair", id: `pair-${mark.id}` }));
      }
    }
  }
}
