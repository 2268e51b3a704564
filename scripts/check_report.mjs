// Open an HTML report in headless Chromium (Debian's /usr/bin/chromium, driven by playwright-core),
// wait for every <model-viewer> to load its model, collect console errors and page errors, and
// screenshot the first viewer. Prints a JSON summary. Usage: node scripts/check_report.mjs page.html shot.png
import { chromium } from "playwright-core";
import { pathToFileURL } from "node:url";

const [page_path, shot] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"],
});
const page = await browser.newPage({ viewport: { width: 1400, height: 1000 } });
const errors = [];
page.on("console", (m) => { if (m.type() === "error") errors.push(m.text()); });
page.on("pageerror", (e) => errors.push(String(e)));
await page.goto(pathToFileURL(page_path).href);
let viewers = 0;
let loaded = false;
try {
  await page.waitForFunction(() => {
    const v = [...document.querySelectorAll("model-viewer")];
    return v.length > 0 && v.every((m) => m.loaded);
  }, null, { timeout: 90000 });
  loaded = true;
} catch (e) { errors.push("timeout waiting for model-viewer: " + e); }
viewers = await page.evaluate(() => document.querySelectorAll("model-viewer").length);
const first = page.locator("model-viewer").first();
await first.scrollIntoViewIfNeeded();
await page.waitForTimeout(1500);
await first.screenshot({ path: shot });
await browser.close();
process.stdout.write(JSON.stringify({ errors, viewers, loaded }) + "\n");
