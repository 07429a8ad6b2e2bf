"""The surgeon's display in Firefox (issue 15: "works in Chromium and Firefox"), offline, headless.

Debian's ``firefox-esr`` (apt) driven over Marionette, Firefox's own remote protocol, by Mozilla's
``marionette_driver`` (PyPI): no geckodriver binary (none is packaged by Debian or on PyPI from Mozilla) and no
Playwright Firefox (a patched build downloaded from a CDN that CI cannot reach). The same server as the Chromium
test (``test_display_page.display_server``); the drawn axis is read back from the canvas and checked against the
projection of the published axis within 2 px.

Skips with the reason where ``firefox-esr`` or ``marionette_driver`` is missing.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time

import pytest

from conftest import free_port
from display_browser import axis_pixels_js
from test_display_page import assert_axis_on_projection, display_server

# Nothing of Firefox's own goes out (updates, telemetry, captive portal, safe browsing): the page must stand alone.
OFFLINE_PREFS = {
    "app.update.disabledForTesting": True, "browser.shell.checkDefaultBrowser": False, "datareporting.policy.dataSubmissionEnabled": False,
    "toolkit.telemetry.enabled": False, "network.captive-portal-service.enabled": False, "network.connectivity-service.enabled": False,
    "browser.safebrowsing.update.enabled": False, "browser.safebrowsing.malware.enabled": False, "browser.safebrowsing.phishing.enabled": False,
    "extensions.update.enabled": False, "browser.newtabpage.enabled": False, "browser.startup.page": 0, "network.proxy.type": 0,
}


def _pref(name: str, value: object) -> str:
    v = ("true" if value else "false") if isinstance(value, bool) else (str(value) if isinstance(value, int) else f'"{value}"')
    return f'user_pref("{name}", {v});\n'


@pytest.fixture(scope="module")
def firefox(tmp_path_factory):
    exe = shutil.which("firefox-esr") or shutil.which("firefox")
    if exe is None:
        if os.environ.get("CI"):
            pytest.fail("firefox-esr is missing on CI: .ci/run installs it with apt-get install -y firefox-esr")
        pytest.skip("firefox-esr is not installed (apt-get install -y firefox-esr); CI installs it")
    marionette = pytest.importorskip("marionette_driver.marionette", reason="pip install marionette_driver")
    profile = tmp_path_factory.mktemp("firefox-profile")
    port = free_port()
    (profile / "user.js").write_text("".join(_pref(k, v) for k, v in {**OFFLINE_PREFS, "marionette.port": port}.items()))
    proc = subprocess.Popen([exe, "--headless", "--marionette", "--no-remote", "--profile", str(profile), "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, "MOZ_HEADLESS": "1"})
    try:
        client = marionette.Marionette(host="127.0.0.1", port=port)
        client.start_session(timeout=120)
        try:
            yield client
        finally:
            client.delete_session()
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _js(client, expression: str):
    # sandbox=None: run in the page's own scope, where window.drillnav lives (the default sandbox sees the DOM only).
    return client.execute_script(f"return ({expression});", sandbox=None)


def test_the_page_draws_the_axis_on_its_projection_in_firefox(firefox):
    with display_server() as (base, bus, hub):
        firefox.set_window_rect(width=1600, height=1000)
        firefox.navigate(base + "/")
        deadline = time.monotonic() + 30
        checked = 0
        while checked < 2 and time.monotonic() < deadline:
            ready = _js(firefox, "Object.keys(window.drillnav.views).length === 3 && Object.values(window.drillnav.views).every(v => v.drawn && v.drawn.segment && !v.drawn.stale)")
            if not ready:
                time.sleep(0.2)
                continue
            got = _js(firefox, f"({axis_pixels_js})()")
            if any(g["drawn"]["stale"] for g in got.values()):
                continue  # late on a loaded machine: greyed, as it must be
            assert_axis_on_projection(got, bus)
            checked += 1
            time.sleep(0.3)
        assert checked == 2, f"Firefox drew no live axis on all three views within 30 s: {_js(firefox, 'Object.keys(window.drillnav.views)')}"
        assert _js(firefox, "window.drillnav.framesDrawn") > 10 and _js(firefox, "window.drillnav.repeats") == 0
        assert _js(firefox, "window.drillnav.camerasShown") >= 1  # createImageBitmap with resizeWidth: supported here too
        assert hub.clients >= 1
