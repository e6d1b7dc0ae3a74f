// Shared by the pages: JSON fetch with readable errors, and the operator token for writes.
function toLogin() {
  location.assign(`/login?next=${encodeURIComponent(location.pathname + location.search)}`);
}

export async function getJSON(url) {
  const response = await fetch(url, { headers: { Accept: "application/json" } });
  if (response.status === 401) { toLogin(); throw new Error("log in first"); }
  const body = await response.json().catch(() => ({}));
  if (!response.ok) throw new Error(body.error ? `${body.error.type}: ${body.error.message}` : response.statusText);
  return body;
}

export async function send(method, url, body = {}) {
  const headers = { "Content-Type": "application/json" };
  const token = sessionStorage.getItem("tbp-token");
  if (token) headers.Authorization = `Bearer ${token}`;
  let response = await fetch(url, { method, headers, body: JSON.stringify(body) });
  if (response.status === 401) {
    const given = prompt("This action needs the operator token:");
    if (!given) throw new Error("no token given");
    sessionStorage.setItem("tbp-token", given.trim());
    return send(method, url, body);
  }
  const reply = await response.json().catch(() => ({}));
  if (!response.ok) throw new Error(reply.error ? `${reply.error.type}: ${reply.error.message}` : response.statusText);
  return reply;
}

export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (key === "class") node.className = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (key === "dataset") Object.assign(node.dataset, value);
    else node.setAttribute(key, value);
  }
  for (const child of children) if (child !== null && child !== undefined) node.append(child);
  return node;
}

export const fmt = (x, digits = 1) => (x === null || x === undefined || Number.isNaN(x) ? "–" : Number(x).toFixed(digits));

// How a scan ended, from its manifest's state (the list and the viewer say it alike): a pill's
// class and label, and the lines saying why (the reason, the missing images per phone).
const ENDED = {
  complete: "complete",
  partial: "partial: images missing",
  aborted: "aborted",
  fault: "stopped by a fault",
  incomplete: "incomplete (interrupted)",
};
export function ending(scan) {
  if (scan.in_progress) return { kind: "busy", label: "in progress", why: [], done: false };
  const why = [];
  if (scan.reason && scan.state !== "partial") why.push(scan.reason);
  if (scan.missing) why.push(scan.missing);
  return { kind: scan.state, label: ENDED[scan.state] || scan.state, why, done: scan.state === "complete" };
}

// A DICOM person name "Family^Given^Middle^Prefix^Suffix" as a person reads it: "Family, Given Middle".
export function personName(pn) {
  const [family = "", given = "", middle = "", prefix = "", suffix = ""] = (pn || "").split("^");
  const first = [prefix, given, middle].filter(Boolean).join(" ");
  return [family, first].filter(Boolean).join(", ") + (suffix ? ` ${suffix}` : "");
}
