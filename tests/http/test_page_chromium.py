#!/usr/bin/python3
"""The web page in a real headless Chromium (Debian's chromium + chromium-driver, driven by
python3-selenium) against the real surfel-server: upload a sampled shape, check the cloud's
numbers, orbit the preview, render, wait for the image and check that it decoded and has
non-background pixels (and that the render used the orbited camera); a malformed file shows the
server's message; simplify replaces the preview; cancel in the job list cancels."""
import argparse
import math
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from surfel_http import Server, post_json, request  # noqa: E402

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


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--server-bin", required=True)
    ap.add_argument("--work-dir", required=True)
    a = ap.parse_args()
    server = Server(a.server_bin, a.work_dir, ["--workers", "1", "--grace", "0"])
    shape = os.path.join(a.work_dir, "torus.ply")
    open(shape, "wb").write(torus_ply(4000))
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

        # Simplify: the result replaces the preview and can be downloaded.
        Select(driver.find_element(By.ID, "method")).select_by_visible_text("VOXEL")
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
