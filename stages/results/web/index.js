(function () {
  const rows = Array.from(document.querySelectorAll("table.cells tbody tr"));
  const text = document.getElementById("filter");
  const selects = Array.from(document.querySelectorAll("select[data-key]"));
  const count = document.getElementById("shown");
  function apply() {
    const words = text.value.toLowerCase().split(/\s+/).filter(Boolean);
    let shown = 0;
    for (const r of rows) {
      const ok = selects.every((s) => !s.value || r.dataset[s.dataset.key] === s.value) &&
        words.every((w) => r.dataset.text.includes(w));
      r.hidden = !ok;
      shown += ok ? 1 : 0;
    }
    count.textContent = shown;
  }
  text.addEventListener("input", apply);
  selects.forEach((s) => s.addEventListener("change", apply));
  for (const th of document.querySelectorAll("table.cells th")) {
    th.addEventListener("click", () => {
      const table = th.closest("table"), body = table.tBodies[0], col = th.cellIndex;
      const up = th.dataset.dir !== " \u25b2";
      table.querySelectorAll("th").forEach((h) => delete h.dataset.dir);
      th.dataset.dir = up ? " \u25b2" : " \u25bc";
      const key = (r) => { const c = r.cells[col]; return c.dataset.v !== undefined ? c.dataset.v : c.textContent; };
      const num = (v) => (v === "" ? NaN : Number(v));
      // numbers as numbers, text as text; empty cells last in either direction
      const sorted = Array.from(body.rows).sort((a, b) => {
        const x = key(a), y = key(b);
        if ((x === "") !== (y === "")) return x === "" ? 1 : -1;
        const nx = num(x), ny = num(y);
        const d = !isNaN(nx) && !isNaN(ny) ? nx - ny : x.localeCompare(y);
        return up ? d : -d;
      });
      sorted.forEach((r) => body.appendChild(r));
    });
  }
  apply();
  // milliseconds since navigation start when the table became interactive (read by the browser test)
  document.body.dataset.ready = String(Math.round(performance.now()));
})();
