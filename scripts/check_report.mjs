// Open a page of the HTML report in headless Chromium (Debian's /usr/bin/chromium, driven by
// playwright-core) and report what a reader would meet, as one JSON line on stdout.
//
//   node scripts/check_report.mjs index PAGE SHOT [--filter WORDS] [--mesh ID]
//       the index: console errors, time until its script made the table interactive (ms after
//       navigation start), rows, rows left by the text filter and by the mesh selector, a
//       sort by the quality column, and a screenshot of the first screen
//   node scripts/check_report.mjs cell PAGE SHOT [--page-shot FILE]
//       a cell page: console errors, every file it requested, its 3D viewer loaded (with the
//       learned light, then the studio light: SHOT and SHOT's name + _studio), a gallery
//       thumbnail clicked; --page-shot: the first screen of the page (the README's picture)
//   node scripts/check_report.mjs downloads PAGE SHOT --into DIR
//       every download link (a[download]) clicked: the browser's download saved into DIR as
//       <k>-<suggested name>, with the link's href, label and the download's failure (null)
//   node scripts/check_report.mjs single PAGE SHOT
//       a one-file report: every viewer scrolled into view and loaded; a screenshot of the first
//
// PAGE is a file path or an http(s) URL.
import { chromium } from "playwright-core";
import { pathToFileURL } from "node:url";

const [mode, target, shot, ...rest] = process.argv.slice(2);
const option = (name) => { const i = rest.indexOf(name); return i >= 0 ? rest[i + 1] : undefined; };
const url = /^https?:/.test(target) ? target : pathToFileURL(target).href;
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"],
});
const page = await browser.newPage({ viewport: { width: 1400, height: 1000 }, acceptDownloads: true });
const errors = [];
const requests = [];
page.on("console", (m) => { if (m.type() === "error") errors.push(m.text()); });
page.on("pageerror", (e) => errors.push(String(e)));
page.on("requestfailed", (r) => errors.push("request failed: " + r.url() + " " + (r.failure() || {}).errorText));
page.on("request", (r) => requests.push(r.url()));
const out = { mode, errors, requests };
const visible = () => page.evaluate(() => [...document.querySelectorAll("table.cells tbody tr")].filter((r) => !r.hidden).length);

if (mode === "index") {
  const t0 = Date.now();
  await page.goto(url, { waitUntil: "load" });
  await page.waitForFunction(() => document.body.dataset.ready !== undefined, null, { timeout: 30000 });
  out.load_ms = Date.now() - t0;
  out.interactive_ms = await page.evaluate(() => Number(document.body.dataset.ready));
  out.rows = await visible();
  await page.screenshot({ path: shot });
  const words = option("--filter");
  if (words !== undefined) {
    await page.fill("#filter", words);
    out.filtered_rows = await visible();
    out.shown_label = await page.textContent("#shown");
    await page.fill("#filter", "");
  }
  const mesh = option("--mesh");
  if (mesh !== undefined) {
    await page.selectOption("select[data-key=mesh]", mesh);
    out.mesh_rows = await visible();
    out.mesh_values = await page.evaluate(() => [...new Set([...document.querySelectorAll("table.cells tbody tr")].filter((r) => !r.hidden).map((r) => r.dataset.mesh))]);
    await page.selectOption("select[data-key=mesh]", "");
  }
  const header = page.locator("table.cells th", { hasText: "quality" }).first();
  const column = () => page.evaluate(() => [...document.querySelector("table.cells").tBodies[0].rows].map((r) => {
    const i = [...r.closest("table").tHead.rows[0].cells].findIndex((h) => h.textContent.startsWith("quality"));
    return r.cells[i].dataset.v === "" ? null : Number(r.cells[i].dataset.v);
  }));
  if (await header.count()) {
    await header.click();
    out.sorted_quality = await column();
    await header.click();
    out.sorted_quality_desc = await column();
  }
  out.figures = await page.evaluate(() => document.querySelectorAll(".figure img").length);
  out.skipped = await page.evaluate(() => [...document.querySelectorAll(".skipped")].map((p) => p.textContent));
} else if (mode === "cell" || mode === "single") {
  await page.goto(url, { waitUntil: "load" });
  const viewers = page.locator("model-viewer");
  out.viewers = await viewers.count();
  out.loaded = 0;
  for (let i = 0; i < out.viewers; i++) {
    const v = viewers.nth(i);
    await v.scrollIntoViewIfNeeded();
    try {
      const at = await v.evaluate((m) => new Promise((resolve, reject) => {
        if (m.loaded) return resolve(performance.now());
        m.addEventListener("load", () => resolve(performance.now()), { once: true });
        m.addEventListener("error", (e) => reject(new Error("model-viewer error " + JSON.stringify(e.detail))), { once: true });
        setTimeout(() => reject(new Error("timeout")), 90000);
      }));
      // ms after navigation start when the (first) viewer had its model
      if (out.loaded === 0) out.viewer_ms = Math.round(at);
      out.loaded += 1;
    } catch (e) { errors.push("viewer " + i + ": " + e); }
  }
  if (out.viewers) {
    const first = viewers.first();
    await first.scrollIntoViewIfNeeded();
    const env = await first.evaluate((m) => m.environmentImage || "");
    out.environment = env.length > 100 ? env.slice(0, 40) + "..." + env.slice(-20) : env;
    await page.waitForTimeout(1500);
    await first.screenshot({ path: shot });
    const studio = page.locator("button[data-light=studio]").first();
    if (await studio.count()) {
      await studio.click();
      out.environment_studio = await first.evaluate((m) => m.environmentImage);
      await page.waitForTimeout(1000);
      await first.screenshot({ path: shot.replace(/\.png$/, "_studio.png") });
      await page.locator("button[data-light=learned]").first().click();
      await page.waitForTimeout(1000);
    }
    const pageShot = option("--page-shot");
    if (pageShot !== undefined) {
      await page.evaluate(() => window.scrollTo(0, 0));
      await page.waitForTimeout(500);
      await page.screenshot({ path: pageShot });
    }
  } else {
    await page.screenshot({ path: shot });
  }
  if (mode === "single" && out.viewers > 1) {
    // each viewer's own buttons: studio under the first leaves the others under their learned light
    await page.locator("button[data-light=studio]").first().click();
    out.environments_after_first_studio = await viewers.evaluateAll((ms) => ms.map((m) => (m.environmentImage || "").slice(-20)));
  }
  out.galleries = await page.evaluate(() => document.querySelectorAll(".gallery").length);
  const pick = page.locator(".gallery .picks img").nth(1);
  if (await pick.count()) {
    await pick.click();
    out.gallery_switch = await page.evaluate(() => {
      const g = document.querySelector(".gallery");
      return g.querySelector("img.main").getAttribute("src") === g.querySelectorAll(".picks img")[1].getAttribute("src");
    });
  }
} else if (mode === "downloads") {
  // every download link of the page clicked as a reader would: the browser's download saved under
  // --into DIR as <k>-<suggested name>; what each link said and what arrived
  await page.goto(url, { waitUntil: "load" });
  const into = option("--into") || ".";
  const anchors = page.locator("a[download]");
  out.downloads = [];
  for (let i = 0; i < await anchors.count(); i++) {
    const a = anchors.nth(i);
    const link = await a.evaluate((el) => ({ href: el.getAttribute("href"), name: el.getAttribute("download"), label: el.textContent }));
    try {
      const [download] = await Promise.all([page.waitForEvent("download", { timeout: 30000 }), a.click()]);
      const saved = `${into}/${i}-${download.suggestedFilename()}`;
      await download.saveAs(saved);
      out.downloads.push({ ...link, suggested: download.suggestedFilename(), saved, failure: await download.failure() });
    } catch (e) { errors.push("download " + link.href + ": " + e); }
  }
  await page.screenshot({ path: shot });
} else {
  errors.push("unknown mode " + mode + " (index, cell, single or downloads)");
}
await browser.close();
process.stdout.write(JSON.stringify(out) + "\n");
