(function () {
  function blobUrl(b64, type, name) {
    const bin = atob(b64), bytes = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    // model-viewer picks its HDR loader by the URL's ending, so the name rides in the fragment
    return URL.createObjectURL(new Blob([bytes], { type })) + "#" + name;
  }
  // each viewer's light buttons sit beside it, in the same .viewer box (one page may hold many)
  const buttons = (mv) => (mv.closest(".viewer") || mv.parentElement).querySelectorAll("button[data-light]");
  function setLight(mv, which) {
    mv.environmentImage = which === "learned" && mv.dataset.learned ? mv.dataset.learned : "neutral";
    for (const b of buttons(mv)) b.classList.toggle("on", b.dataset.light === which);
    mv.dataset.light = which;
  }
  function start(mv) {
    if (mv.dataset.started) return;
    mv.dataset.started = "1";
    // keep a light chosen before the model arrived
    const apply = (glb, hdr) => {
      mv.dataset.learned = hdr || "";
      setLight(mv, mv.dataset.light || (hdr ? "learned" : "studio"));
      mv.src = glb;
    };
    if (location.protocol === "file:" && mv.dataset.packed) {
      const s = document.createElement("script");
      s.src = mv.dataset.packed;
      s.onload = () => {
        const a = window.TANGO_CELL_ASSETS;
        apply(blobUrl(a.glb, "model/gltf-binary", "model.glb"), a.hdr ? blobUrl(a.hdr, "application/octet-stream", "light.hdr") : "");
      };
      s.onerror = () => console.error("could not load " + mv.dataset.packed);
      document.head.appendChild(s);
    } else {
      apply(mv.dataset.glb, mv.dataset.hdr);
    }
  }
  for (const mv of document.querySelectorAll("model-viewer[data-glb]")) {
    if ("IntersectionObserver" in window) {
      const io = new IntersectionObserver((es) => { if (es.some((e) => e.isIntersecting)) { io.disconnect(); start(mv); } });
      io.observe(mv);
    } else start(mv);
    for (const b of buttons(mv)) b.addEventListener("click", () => setLight(mv, b.dataset.light));
  }
  for (const g of document.querySelectorAll(".gallery")) {
    const main = g.querySelector("img.main"), caption = g.querySelector(".caption");
    for (const p of g.querySelectorAll(".picks img")) {
      p.addEventListener("click", () => {
        main.src = p.getAttribute("src");
        caption.textContent = p.alt;
        g.querySelectorAll(".picks img").forEach((q) => q.classList.toggle("on", q === p));
      });
    }
  }
})();
