// Small DOM helpers. Telemetry text only ever goes into textContent, never into markup.

const SVG_NS = "http://www.w3.org/2000/svg";

/** An HTML element with attributes and children (strings become text nodes). */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs)) node.setAttribute(name, value);
  node.append(...children.filter((c) => c !== null && c !== undefined));
  return node;
}

/** An SVG element with attributes, appended to `parent` when given. */
export function svg(tag, attrs = {}, parent = null) {
  const node = document.createElementNS(SVG_NS, tag);
  for (const [name, value] of Object.entries(attrs)) node.setAttribute(name, value);
  if (parent) parent.appendChild(node);
  return node;
}

/** A number with `digits` decimals, or "–" when missing or not finite. */
export function fmt(value, digits = 2) {
  return typeof value === "number" && Number.isFinite(value) ? value.toFixed(digits) : "–";
}

/** A vector's numbers with `digits` decimals, comma-separated, or "–" when it is missing. */
export function vector(values, digits = 2) {
  return Array.isArray(values) ? values.map((x) => fmt(x, digits)).join(", ") : "–";
}

/** Replace the rows of a table body: each row is a list of cells, a cell text or [text, class]. */
export function setRows(tbody, rows) {
  tbody.replaceChildren(...rows.map((cells) => el("tr", {}, ...cells.map((cell) => {
    const [text, cls] = Array.isArray(cell) ? cell : [cell, ""];
    return el("td", cls ? { class: cls } : {}, String(text));
  }))));
}

/** A badge's text and state class (ok, degraded, lost, unknown). */
export function setBadge(node, text, state) {
  node.textContent = text;
  node.className = `badge ${state}`;
  node.dataset.state = state;
}
