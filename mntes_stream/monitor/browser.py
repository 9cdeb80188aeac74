"""Headless Chromium driven by selenium: how the tests and the bench look at the page.

Uses Debian's ``chromium`` and ``chromium-driver`` packages (``.ci/run``
installs them) and the ``selenium`` pip package (``test`` extra). Nothing
here downloads a browser.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from mntes_stream.errors import ConfigError

__all__ = ["CHROMIUM_FLAGS", "find_chromium", "headless_chromium", "page_state"]

# Root-safe, quiet, offline: no sandbox (root), no GPU, no phoning home, a fresh profile.
CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-dev-shm-usage",
)


def find_chromium() -> tuple[str, str] | None:
    """``(chromium binary, chromedriver)`` when both are installed, else None."""
    binary = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver") or ("/usr/bin/chromedriver" if Path("/usr/bin/chromedriver").exists() else None)
    return (binary, driver) if binary and driver else None


def headless_chromium(window: tuple[int, int] = (1400, 1300), profile_dir: str | None = None):
    """A selenium ``webdriver.Chrome`` on headless Chromium with :data:`CHROMIUM_FLAGS`; call ``quit()``.

    Raises
    ------
    ConfigError
        When chromium/chromedriver are not installed.
    """
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    found = find_chromium()
    if found is None:
        raise ConfigError("chromium and chromedriver not found: apt-get install -y chromium chromium-driver")
    binary, driver = found
    opts = webdriver.ChromeOptions()
    for flag in CHROMIUM_FLAGS:
        opts.add_argument(flag)
    opts.add_argument(f"--window-size={window[0]},{window[1]}")
    opts.add_argument(f"--user-data-dir={profile_dir or tempfile.mkdtemp(prefix='mntes-chromium-')}")
    opts.binary_location = binary
    return webdriver.Chrome(service=Service(driver), options=opts)


# What the page itself holds and draws (read through the browser, not from the server).
_STATE_JS = """
const M = window.mntesMonitor || {};
const data = (id) => { const el = document.getElementById(id); return el && el.data ? el.data : []; };
const grid = data('grid')[0];
const gridCells = {};
if (grid) {
  const cell = (t, z) => { if (t) { const [id, rest] = t.split(': '); gridCells[id] = {state: rest.split(' · ')[0], z: z}; } };
  if (grid.type === 'heatmap') grid.text.forEach((row, i) => row.forEach((t, j) => cell(t, grid.z[i][j])));
  else grid.text.forEach((t, i) => cell(t, grid.marker.color[i]));  // the sky layout: one marker per detector
}
const axisText = (id) => { const el = document.getElementById(id);
  return el && el.layout && el.layout.annotations ? el.layout.annotations.map(a => a.text) : []; };
const xaxis = (id) => { const el = document.getElementById(id);
  return el && el._fullLayout && el._fullLayout.xaxis ? {visible: el._fullLayout.xaxis.visible,
    range: el._fullLayout.xaxis.range} : null; };
const spec = document.getElementById('spectrum');
return {
  updates: M.updates || 0,
  fresh: M.fresh || null,
  fresh_changes: M.freshChanges || [],
  badge: {text: document.getElementById('fresh').textContent, cls: document.getElementById('fresh').className},
  conn: document.getElementById('conn').textContent,
  clicks: M.clicks || 0,
  annotations: {timestreams: axisText('timestreams'), spectrum: axisText('spectrum'), hk: axisText('hk')},
  xaxes: {timestreams: xaxis('timestreams'), hk: xaxis('hk')},
  focal_metric: M.last && M.last.focal ? M.last.focal.metric : null,
  window_s: M.last ? M.last.window_s : null,
  freshness: M.last ? M.last.freshness : null,
  last_t_server_ns: M.last ? M.last.t_ns : null,
  renders: M.renders || [],
  errors: M.errors || [],
  selection: M.selection || [],
  timestreams: data('timestreams').map(t => ({name: t.name, n: t.x.length,
      finite: t.y.filter(v => v !== null && Number.isFinite(v)).length})),
  spectrum: data('spectrum').map(t => ({name: t.name, n: t.x.length,
      finite: t.y.filter(v => v !== null && Number.isFinite(v)).length})),
  harmonics: spec && spec.layout && spec.layout.shapes ? spec.layout.shapes.map(s => s.x0) : [],
  grid: gridCells,
  grid_type: grid ? grid.type : null,
  legend: document.getElementById('legend') ? document.getElementById('legend').innerText : '',
  hk: data('hk').map(t => ({name: t.name, n: t.x.length})),
  leakage: data('leakage').map(t => ({name: t.name, x: t.x, y: t.y,
      err: t.error_y && t.error_y.array ? t.error_y.array : null})),
  leakage_notes: axisText('leakage'),
  leakage_info: document.getElementById('leakage-info') ? document.getElementById('leakage-info').textContent : '',
  health: document.getElementById('health') ? document.getElementById('health').innerText : '',
};
"""


def page_state(driver) -> dict:
    """What the page shows: updates drawn, render latencies, chart points, grid cell states, panels' text."""
    return driver.execute_script(_STATE_JS)
