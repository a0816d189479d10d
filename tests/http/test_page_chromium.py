#!/usr/bin/python3
"""The web page in a real headless Chromium (Debian's chromium + chromium-driver, driven by
python3-selenium) against the real surfel-server: upload a sampled shape, check the cloud's
numbers, orbit the preview, render, wait for the image and check that it decoded and has
non-background pixels (and that the render used the orbited camera); a malformed file shows the
server's message; simplify, resample (particle, to a count) and a boolean (union with an uploaded
second solid, moved by the form's transform) each replace the preview with their result and show
its point count; a resample the server refuses shows the server's message; mls keeps the count; cancel in the job list
cancels. With ../shared/data/bunny.ply present it also times Render click -> image for the bunny
at 512x512 in the page (browser clock; reported, never asserted) and writes it to --bench-out."""
import argparse
import datetime
import json
import math
import statistics
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from surfel_http import Server, post_json, request, sphere_ply  # noqa: E402

from selenium import webdriver  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.common.exceptions import NoSuchElementException, StaleElementReferenceException  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402


def torus_ply(n, R=1.0, r=0.4):
    """n points sampled on a torus (a golden-angle lattice over its two angles), ASCII PLY."""
    golden = math.pi * (3 - math.sqrt(5))
    lines = ["ply", "format ascii 1.0", f"element vertex {n}",
             "property float x", "property float y", "property float z", "end_header"]
    for i in range(n):
        u = 2 * math.pi * (i + 0.5) / n
        v = golden * i
        lines.append(f"{(R + r * math.cos(v)) * math.cos(u):.6f} {(R + r * math.cos(v)) * math.sin(u):.6f} "
                     f"{r * math.sin(v):.6f}")
    return ("\n".join(lines) + "\n").encode()


def browser():
    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for flag in ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--window-size=1280,1000"]:
        opts.add_argument(flag)
    return webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)


def time_bunny_render(driver, server, a):
    """Render click -> image loaded, for the bunny at 512x512 (1 sample/pixel, the page's default
    light), on the browser's clock: the page submits, follows the events, loads the PNG. Each
    round moves the camera a little so no two jobs are the same."""
    wait = WebDriverWait(driver, 120, poll_frequency=0.05)
    driver.find_element(By.ID, "file").send_keys(os.path.abspath(a.bunny))
    wait.until(lambda d: d.find_element(By.ID, "upload-status").text.startswith("stored")
               and d.find_element(By.ID, "cloud-points").text not in ("", "4,000")
               and d.find_element(By.ID, "preview-status").text.split()[0]
               == d.find_element(By.ID, "cloud-points").text)  # the preview is the bunny's, framed
    for field, value in [("width", "512"), ("height", "512"), ("spp", "1")]:
        el = driver.find_element(By.ID, field)
        el.clear()
        el.send_keys(value)
    preview = driver.find_element(By.ID, "preview")
    times, job_ms = [], []  # click -> image on the browser's clock; the job's created -> finished
    for _ in range(a.bunny_rounds):
        ActionChains(driver).move_to_element(preview).click_and_hold().move_by_offset(15, 0).release().perform()
        wait.until(lambda d: d.find_element(By.ID, "render").is_enabled())
        driver.execute_script("""
            window.__renderMs = null;
            const img = document.getElementById('render-img');
            const t0 = performance.now();
            img.addEventListener('load', () => { window.__renderMs = performance.now() - t0; }, { once: true });
            document.getElementById('render').click();""")
        wait.until(lambda d: d.execute_script("return window.__renderMs") is not None
                   or d.find_element(By.ID, "error").is_displayed())
        assert not driver.find_element(By.ID, "error").is_displayed(), driver.find_element(By.ID, "error").text
        times.append(driver.execute_script("return window.__renderMs"))
        job_id = driver.find_element(By.ID, "png-download").get_attribute("href").split("/")[-2]
        job = request("GET", f"{server.base}/v1/jobs/{job_id}").json()
        job_ms.append(int(job["finishedUnixMs"]) - int(job["createdUnixMs"]))
    points = driver.find_element(By.ID, "cloud-points").text
    result = {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
              "what": "Render click -> PNG loaded in the page, bunny.ply at 512x512, 1 spp",
              "points": points, "rounds_ms": [round(t) for t in times], "median_ms": round(statistics.median(times)),
              "job_rounds_ms": job_ms, "job_median_ms": round(statistics.median(job_ms)),
              "load_1min": os.getloadavg()[0], "cores": os.cpu_count()}
    print(f"--  bunny ({points} points) 512x512 Render click -> image: median {result['median_ms']} ms "
          f"over {len(times)} round(s) {result['rounds_ms']}, of which the job (created -> finished) "
          f"{result['job_median_ms']} ms (load {result['load_1min']:.1f}; not asserted)")
    if a.bench_out:
        with open(a.bench_out, "w") as f:
            json.dump(result, f, indent=1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--server-bin", required=True)
    ap.add_argument("--work-dir", required=True)
    ap.add_argument("--bunny", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                    "../../../shared/data/bunny.ply"),
                    help="the bunny for the Render click -> image timing (skipped when absent)")
    ap.add_argument("--bunny-rounds", type=int, default=1)
    ap.add_argument("--bench-out", help="write the timing here as JSON")
    a = ap.parse_args()
    server = Server(a.server_bin, a.work_dir, ["--workers", "1", "--grace", "0"])
    shape = os.path.join(a.work_dir, "torus.ply")
    open(shape, "wb").write(torus_ply(4000))
    ball = os.path.join(a.work_dir, "ball.ply")
    open(ball, "wb").write(sphere_ply(3000, binary=True))
    bad = os.path.join(a.work_dir, "broken.ply")
    open(bad, "wb").write(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\nzz\n")
    driver = None
    t0 = time.monotonic()
    try:
        driver = browser()
        wait = WebDriverWait(driver, 40, poll_frequency=0.1)
        driver.get(server.base + "/")
        wait.until(lambda d: d.execute_script("return document.readyState") == "complete")

        # Upload -> the cloud's numbers.
        driver.find_element(By.ID, "file").send_keys(shape)
        wait.until(lambda d: d.find_element(By.ID, "cloud-points").text == "4,000")
        wait.until(lambda d: d.find_element(By.ID, "preview-status").text != "no cloud yet")
        cloud_id = driver.find_element(By.ID, "cloud-id").text
        assert len(cloud_id) == 64, cloud_id
        assert "(" in driver.find_element(By.ID, "cloud-bounds").text
        status = driver.find_element(By.ID, "preview-status").text
        print(f"ok  upload ({time.monotonic() - t0:.1f} s); preview: {status}")
        assert "three.js did not load" not in status, status

        # Orbit the preview: a drag on it turns the camera.
        preview = driver.find_element(By.ID, "preview")
        ActionChains(driver).move_to_element(preview).click_and_hold().move_by_offset(120, 40).release().perform()

        # Render -> progress -> the PNG.
        for field, value in [("width", "96"), ("height", "72")]:
            el = driver.find_element(By.ID, field)
            el.clear()
            el.send_keys(value)
        wait.until(lambda d: d.find_element(By.ID, "render").is_enabled())
        driver.find_element(By.ID, "render").click()
        wait.until(lambda d: d.execute_script(
            "const i = document.getElementById('render-img'); return i.complete && i.naturalWidth > 0;")
            or d.find_element(By.ID, "error").is_displayed())
        error = driver.find_element(By.ID, "error")
        assert not error.is_displayed(), error.text
        size, lit = driver.execute_script("""
            const img = document.getElementById('render-img');
            const c = document.createElement('canvas');
            c.width = img.naturalWidth; c.height = img.naturalHeight;
            const g = c.getContext('2d');
            g.drawImage(img, 0, 0);
            const d = g.getImageData(0, 0, c.width, c.height).data;
            const bg = [d[0], d[1], d[2]];
            let lit = 0;
            for (let i = 0; i < d.length; i += 4)
              if (Math.abs(d[i] - bg[0]) + Math.abs(d[i + 1] - bg[1]) + Math.abs(d[i + 2] - bg[2]) > 30) lit++;
            return [[c.width, c.height], lit];""")
        assert size == [96, 72], size
        assert lit > 0.05 * 96 * 72, lit
        jobs = request("GET", server.base + "/v1/jobs?state=SUCCEEDED").json()["jobs"]
        render = next(j for j in jobs if j["type"] == "render")
        eye = render["spec"]["render"]["camera"]["eye"]
        assert abs(eye.get("x", 0)) > 0.1, f"the render did not use the orbited camera: eye {eye}"
        assert driver.find_element(By.ID, "png-download").get_attribute("download").endswith(".png")
        print(f"ok  render: {size[0]}x{size[1]} image, {lit} non-background pixels, eye {eye} "
              f"({time.monotonic() - t0:.1f} s)")

        # Simplify: the result replaces the preview and can be downloaded. The representative is
        # off for particle simulation, on again for the others.
        Select(driver.find_element(By.ID, "method")).select_by_visible_text("PARTICLE")
        assert not driver.find_element(By.ID, "representative").is_enabled()
        Select(driver.find_element(By.ID, "method")).select_by_visible_text("VOXEL")
        assert driver.find_element(By.ID, "representative").is_enabled()
        Select(driver.find_element(By.ID, "representative")).select_by_visible_text("MEMBER")
        target = driver.find_element(By.ID, "target")
        target.clear()
        target.send_keys("500")
        wait.until(lambda d: d.find_element(By.ID, "simplify").is_enabled())
        driver.find_element(By.ID, "simplify").click()
        wait.until(lambda d: d.find_element(By.ID, "simplify-status").text.startswith("done")
                   or d.find_element(By.ID, "error").is_displayed())
        assert not driver.find_element(By.ID, "error").is_displayed(), driver.find_element(By.ID, "error").text
        shown = driver.find_element(By.ID, "preview-status").text
        kept = int(shown.split()[0].replace(",", ""))
        assert 0 < kept < 4000, shown
        assert driver.find_element(By.ID, "simplify-download").get_attribute("download").endswith(".ply")
        print(f"ok  simplify: preview shows {shown!r}")

        def run_form(kind, timeout=60):
            """Clicks the form's button; waits for done or an error; returns the status text."""
            WebDriverWait(driver, timeout, 0.1).until(lambda d: d.find_element(By.ID, kind).is_enabled())
            # The click's submit handler sets the status to "submitting…" before its first await,
            # so no status of the previous run can be read as this one's.
            driver.find_element(By.ID, kind).click()
            WebDriverWait(driver, timeout, 0.1).until(
                lambda d: d.find_element(By.ID, f"{kind}-status").text.startswith(("done", "failed"))
                or d.find_element(By.ID, "error").is_displayed())
            return driver.find_element(By.ID, f"{kind}-status").text

        def set_field(field, value):
            el = driver.find_element(By.ID, field)
            el.clear()
            if value != "":
                el.send_keys(value)

        def shown_points():
            return int(driver.find_element(By.ID, "preview-status").text.split()[0].replace(",", ""))

        # Resample (particle, to an exact count): the result replaces the preview.
        Select(driver.find_element(By.ID, "resample-method")).select_by_visible_text("PARTICLE")
        set_field("resample-target", "2500")
        status = run_form("resample")
        assert not driver.find_element(By.ID, "error").is_displayed(), driver.find_element(By.ID, "error").text
        assert status.startswith("done: 2,500 points"), status
        assert shown_points() == 2500, driver.find_element(By.ID, "preview-status").text
        assert driver.find_element(By.ID, "resample-download").get_attribute("download").endswith(".ply")
        print(f"ok  resample: {status!r}")

        # A resample the server refuses (a count and a spacing at once): its words.
        set_field("resample-spacing", "0.05")
        status = run_form("resample")
        shown = driver.find_element(By.ID, "error").text
        assert status == "failed" and shown == "resample.target: give target or spacing, not both", (status, shown)
        print(f"ok  refused resample shows: {shown!r}")

        # mls smooths every point: the count and spacing fields are off, the result keeps the input's count.
        Select(driver.find_element(By.ID, "resample-method")).select_by_visible_text("MLS")
        assert not driver.find_element(By.ID, "resample-target").is_enabled()
        status = run_form("resample")
        assert not driver.find_element(By.ID, "error").is_displayed(), driver.find_element(By.ID, "error").text
        assert status.startswith("done: 4,000 points") and shown_points() == 4000, status
        print(f"ok  resample mls: {status!r}")

        # Boolean: B uploaded in the form, moved onto the torus' tube; union -> the preview.
        driver.find_element(By.ID, "file-b").send_keys(ball)
        wait.until(lambda d: d.find_element(By.ID, "upload-b-status").text.startswith("B: ball.ply, 3,000 points"))
        Select(driver.find_element(By.ID, "boolean-op")).select_by_value("UNION")
        for field, value in [("b-tx", "1"), ("b-ty", "0"), ("b-tz", "0"), ("b-deg", "30"), ("b-scale", "0.5")]:
            set_field(field, value)
        status = run_form("boolean")
        assert not driver.find_element(By.ID, "error").is_displayed(), driver.find_element(By.ID, "error").text
        assert status.startswith("done: "), status
        n = shown_points()
        assert status.startswith(f"done: {n:,} points") and "intersection curve" in status, (status, n)
        jobs = request("GET", server.base + "/v1/jobs?state=SUCCEEDED").json()["jobs"]
        spec = next(j for j in jobs if j["type"] == "boolean")["spec"]["boolean"]
        assert spec["transformB"]["scale"] == 0.5 and spec["transformB"]["translation"]["x"] == 1, spec
        assert abs(spec["transformB"]["rotation"][0] - math.cos(math.radians(30))) < 1e-9, spec
        assert driver.find_element(By.ID, "boolean-download").get_attribute("download").endswith(".ply")
        print(f"ok  boolean: {status!r}")

        # A malformed file: the server's message, in words.
        expected = request("POST", server.base + "/v1/clouds?filename=broken.ply", open(bad, "rb").read()).json()
        driver.find_element(By.ID, "file").send_keys(bad)
        wait.until(lambda d: d.find_element(By.ID, "error").is_displayed())
        shown = driver.find_element(By.ID, "error").text
        assert shown == expected["message"], (shown, expected)
        print(f"ok  malformed file shows: {shown!r}")

        # Cancel from the job list.
        slow = post_json(server.base + "/v1/jobs", {"render": {
            "cloudId": cloud_id, "width": 2048, "height": 2048, "samplesPerPixel": 64}}).json()
        row = f"tr[data-job-id='{slow['id']}']"

        def click_cancel(d):  # the list is redrawn every 2 s: a button found may go stale before the click
            try:
                d.find_element(By.CSS_SELECTOR, row + " button.cancel").click()
                return True
            except (NoSuchElementException, StaleElementReferenceException):
                return False
        wait.until(click_cancel)
        wait.until(lambda d: request("GET", f"{server.base}/v1/jobs/{slow['id']}").json()["state"] == "CANCELLED")
        wait.until(lambda d: "cancelled" in d.execute_script(
            "const r = document.querySelector(arguments[0]); return r ? r.textContent : '';", row))
        print(f"ok  cancel from the job list ({time.monotonic() - t0:.1f} s)")

        if os.path.exists(a.bunny):
            time_bunny_render(driver, server, a)
        else:
            print(f"--  no {a.bunny}: Render click -> image timing skipped")
    except BaseException:
        if driver:
            try:
                print("page error box:", driver.find_element(By.ID, "error").text)
                for field in ["upload-status", "preview-status", "render-status", "simplify-status"]:
                    print(f"{field}:", driver.find_element(By.ID, field).text)
                print("jobs:", request("GET", server.base + "/v1/jobs").body.decode()[:3000])
                for entry in driver.get_log("browser"):
                    print("console:", entry)
            except Exception as e:  # the browser itself may be gone
                print("no browser log:", e)
        print("server log:\n" + server.read_log())
        raise
    finally:
        if driver:
            driver.quit()
        server.stop()
    print("page test passed")


if __name__ == "__main__":
    main()
