// The operator station's page in a real browser (Debian's chromium, headless, driven by
// playwright-core): the page loads and goes live, the camera thumbnails update, the session is
// set, Start then Success (the buttons) record an episode that appears in the table, "to
// failure" relabels it, "trash" (confirmed) moves it out of the table.
//
// Last, the station is frozen (SIGSTOP to the processes matching STATION_PATTERN): the page
// says it is disconnected; thawed (SIGCONT), the page says it is live again, by itself.
//
// usage: node station_browser.mjs URL OUT_DIR STATION_PATTERN
// writes OUT_DIR/{cams_before,cams_after,page}.png; prints JSON lines, one per stage
// ({"stage": ..., ...}); exits 1 with the reason on stderr when a stage times out.
import { chromium } from "playwright-core";
import { execSync } from "node:child_process";

const [url, out, stationPattern] = process.argv.slice(2);
const say = (o) => console.log(JSON.stringify(o));
const browser = await chromium.launch({
  executablePath: process.env.LABRIG_CHROMIUM || "/usr/bin/chromium",
  args: ["--no-sandbox", "--disable-gpu"],
});
let page = null;
const fail = async (why) => {
  // What the page said: its own log and state.
  const said = page ? await page.evaluate(() => ({
    log: document.getElementById("log").innerText, loop: document.getElementById("episode_state").textContent,
    conn: document.getElementById("conn").textContent,
  })).catch(() => null) : null;
  console.error(why + "\npage: " + JSON.stringify(said));
  await browser.close();
  process.exit(1);
};
try {
  page = await browser.newPage({ viewport: { width: 1500, height: 950 } });
  page.on("dialog", (d) => d.accept());
  await page.goto(url);
  await page.waitForFunction(() => document.getElementById("conn").textContent === "live", null, { timeout: 20000 });
  // Every camera's thumbnail has loaded.
  await page.waitForFunction(() => {
    const imgs = [...document.querySelectorAll("#cams img")];
    return imgs.length === 5 && imgs.every((i) => i.complete && i.naturalWidth > 0);
  }, null, { timeout: 20000 });
  await page.locator("#cams").screenshot({ path: `${out}/cams_before.png` });
  say({ stage: "live", cameras: await page.locator("#cams img").count() });

  await page.fill("#s_operator", "bob");
  await page.fill("#s_lab", "RAILab");
  await page.fill("#s_building", "B2");
  await page.fill("#s_scene_id", "kitchen_1");
  await page.fill("#s_task", "push the cube forward");
  await page.click("#b_session");
  await page.waitForFunction(() => document.getElementById("session_msg").textContent === "set", null, { timeout: 10000 });
  say({ stage: "session" });

  await page.click("#b_start");
  await page.waitForFunction(() => document.getElementById("episode_state").textContent.includes("Recording"), null, { timeout: 40000 });
  // The expert moves the arm; give it time to move, then the thumbnails again.
  await page.waitForTimeout(2500);
  await page.locator("#cams").screenshot({ path: `${out}/cams_after.png` });
  say({ stage: "recording" });
  await page.click("#b_success");
  const row = page.locator("#episodes tbody tr").first();
  await row.waitFor({ timeout: 30000 });
  await page.waitForFunction(() => {
    const r = document.querySelector("#episodes tbody tr");
    return r && r.cells[1].textContent === "success";
  }, null, { timeout: 30000 });
  const id = await row.getAttribute("data-id");
  const cells = await row.locator("td").allTextContents();
  await row.locator("button.sheetb").click();
  await page.waitForFunction(() => {
    const i = document.querySelector("#sheet img");
    return i && i.complete && i.naturalWidth > 0;
  }, null, { timeout: 20000 });
  await page.screenshot({ path: `${out}/page.png`, fullPage: true });
  say({ stage: "recorded", id, cells });

  await row.locator("button.relabel").click();
  await page.waitForFunction(() => {
    const r = document.querySelector("#episodes tbody tr");
    return r && r.cells[1].textContent === "failure (relabelled)";
  }, null, { timeout: 20000 });
  say({ stage: "relabeled", id });
  await page.locator("#episodes tbody tr").first().locator("button.trash").click();
  await page.waitForFunction(() => document.querySelectorAll("#episodes tbody tr").length === 0, null, { timeout: 20000 });
  say({ stage: "trashed", id });

  execSync(`pkill -STOP -f '${stationPattern}'`);
  try {
    await page.waitForFunction(() => document.getElementById("conn").textContent.startsWith("disconnected"), null, { timeout: 15000 });
  } finally {
    execSync(`pkill -CONT -f '${stationPattern}'`);
  }
  say({ stage: "disconnected" });
  await page.waitForFunction(() => document.getElementById("conn").textContent === "live", null, { timeout: 40000 });
  const log = await page.evaluate(() => document.getElementById("log").innerText);
  say({ stage: "reconnected", said: log.includes("reconnected") });
  await browser.close();
} catch (e) {
  await fail(String(e));
}
