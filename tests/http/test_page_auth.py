#!/usr/bin/python3
"""The page against a server with --auth-tokens, in headless Chromium: without a token the upload
shows the server's UNAUTHENTICATED message; with the token typed into the page's field the upload
works, Render follows the job's events through a signed URL (EventSource sends no headers) and
shows the image fetched with the header. docs/security.md."""
import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from surfel_http import Server  # noqa: E402
from test_page_chromium import browser, torus_ply  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

TOKEN = "page-token-0123456789abcdef"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--server-bin", required=True)
    ap.add_argument("--work-dir", required=True)
    a = ap.parse_args()
    os.makedirs(a.work_dir, exist_ok=True)
    tokens = os.path.join(a.work_dir + "-tokens")
    open(tokens, "w").write(f"web {TOKEN}\n")
    server = Server(a.server_bin, a.work_dir, ["--workers", "1", "--grace", "0", "--auth-tokens", tokens])
    shape = os.path.join(a.work_dir, "torus.ply")
    open(shape, "wb").write(torus_ply(4000))
    driver = None
    try:
        driver = browser()
        wait = WebDriverWait(driver, 40, poll_frequency=0.1)
        driver.get(server.base + "/")  # the page itself is open
        wait.until(lambda d: d.execute_script("return document.readyState") == "complete")
        driver.find_element(By.ID, "file").send_keys(shape)
        wait.until(lambda d: d.find_element(By.ID, "error").is_displayed())
        assert "credentials" in driver.find_element(By.ID, "error").text, driver.find_element(By.ID, "error").text

        field = driver.find_element(By.ID, "token")
        field.send_keys(TOKEN)
        field.send_keys(Keys.TAB)  # "change"
        assert driver.execute_script("return sessionStorage.getItem('surfel-token')") == TOKEN
        driver.execute_script("document.getElementById('file').value = ''")  # the same file again
        driver.find_element(By.ID, "file").send_keys(shape)
        wait.until(lambda d: d.find_element(By.ID, "cloud-points").text == "4,000")
        wait.until(lambda d: d.find_element(By.ID, "render").is_enabled())
        driver.find_element(By.ID, "render").click()
        wait.until(lambda d: d.execute_script(
            "const i = document.getElementById('render-img'); return i.complete && i.naturalWidth > 0;")
            or (d.find_element(By.ID, "error").is_displayed() and "credentials" not in d.find_element(By.ID, "error").text))
        error = driver.find_element(By.ID, "error")
        assert not error.is_displayed() or "credentials" in error.text, error.text
        assert driver.execute_script("return document.getElementById('render-img').naturalWidth") > 0
    except BaseException:
        print("server log:\n" + server.read_log())
        if driver:
            for entry in driver.get_log("browser"):
                print("console:", entry)
        raise
    finally:
        if driver:
            driver.quit()
        server.stop()
    print("page auth test passed")


if __name__ == "__main__":
    main()
