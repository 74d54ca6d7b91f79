"""fwdstep report / run --report: one self-contained HTML page; rendered by headless Chromium
when it is installed (Debian package ``chromium``)."""
import os
import base64
import html.parser
import shutil
import subprocess

import numpy as np
import pytest

from fwdstep.cli.arguments import main

DIAGRAM = """
description: Two decaying joints, x' = g x.
parameters: {g: -1.0}
blocks:
  x: {type: Integrator, shape: [2], initial: [1.0, -2.0]}   # eq. (7)
  k: {type: Gain, gain: g, shape: [2]}
connections:
  - x.y -> k.u
  - k.y -> x.u
simulation: {t_final: 2, step: 0.01, solver: heun}
log:
  - {signal: x.y, label: '$\\Delta q$', unit: rad, components: [joint 1, joint 2]}
plots:
  decay: [x.y, {signals: [x.y], scale: log}]
metrics: {error: x.y}
"""


class _Page(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.links, self.text = [], [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a)
        for key in ("href", "src"):
            if key in a and tag != "img":
                self.links.append(a[key])

    def handle_data(self, data):
        self.text.append(data)


def _parse(path):
    page = _Page()
    page.feed(path.read_text())
    return page


def _run(tmp_path, *extra):
    d = tmp_path / "d.yaml"
    d.write_text(DIAGRAM)
    out = tmp_path / "run"
    code = main(["run", str(d), "-o", str(out), "-q", "--set", "g=-2.5", "--report", *extra])
    assert code == 0
    return out


def test_run_report_is_self_contained_with_every_image(tmp_path):
    out = _run(tmp_path)
    page = _parse(out / "report.html")
    assert page.links == []                                  # nothing fetched from elsewhere
    kinds = []
    for img in page.images:
        head, data = img["src"].split(",", 1)
        assert head.startswith("data:") and head.endswith(";base64")
        raw = base64.b64decode(data)
        kinds.append("png" if raw[:8] == b"\x89PNG\r\n\x1a\n" else
                     "svg" if b"<svg" in raw[:3000] else "?")
    diagram = ["svg"] if shutil.which("dot") else ["svg"]
    assert kinds == diagram + ["png"]                         # the diagram, then 'decay'
    assert base64.b64decode(page.images[1]["src"].split(",", 1)[1]) == \
        (out / "decay.png").read_bytes()
    text = " ".join(page.text)
    # the parameters as run (after --set), the solver settings, the metrics, the status
    assert "-2.5" in text and "heun" in text and "ok" in text
    final = np.linalg.norm([1.0, -2.0]) * np.exp(-2.5 * 2)
    shown = [float(t) for t in page.text if t.strip().replace(".", "", 1).replace("e-", "")
             .replace("-", "").isdigit()]
    assert any(abs(v - final) / final < 1e-3 for v in shown)
    assert "Two decaying joints" in text


def test_report_of_a_sweep_has_its_table_and_figure(tmp_path, capsys):
    d = tmp_path / "d.yaml"
    d.write_text(DIAGRAM)
    out = tmp_path / "sweep"
    assert main(["sweep", str(d), "--grid", "g=-1,-2,-3", "-o", str(out), "-q",
                 "--workers", "1"]) == 0
    assert main(["report", str(out)]) == 0
    page = _parse(out / "report.html")
    text = " ".join(page.text)
    assert "3 ok" in text
    # the sweep figure, the diagram (its path is kept in the parts) and the saved variants
    # overlaid (fwdstep.compare of SWEEP@k)
    assert [img["alt"] for img in page.images] == ["sweep.png", "block diagram",
                                                   "variants compared"]
    html_text = (out / "report.html").read_text()
    assert "3 of 3 saved variants, differences against sweep@0 (g=-1)" in html_text
    assert '<td class="num">-1</td>' in html_text           # the swept value, a number


def test_report_refusals(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 2
    assert capsys.readouterr().err == (f"fwdstep: {tmp_path} holds no saved run, sweep or "
                                       "tuning (no summary.json, sweep.csv or tune.json)\n")
    (tmp_path / "tune.json").write_text("[1, 2]")          # a damaged tuning record: one line
    assert main(["report", str(tmp_path)]) == 2
    assert capsys.readouterr().err == (f"fwdstep: {tmp_path / 'tune.json'}: not a tuning "
                                       "record (no 'initial' and 'best')\n")
    os.remove(tmp_path / "tune.json")
    out = _run(tmp_path)
    mine = tmp_path / "notes.html"
    mine.write_text("my notes")
    assert main(["report", str(out), "-o", str(mine)]) == 2
    assert mine.read_text() == "my notes"
    assert main(["report", str(out), "-o", str(tmp_path / "r.html")]) == 0
    assert main(["report", str(out), "-o", str(tmp_path / "r.html")]) == 0   # its own: replaced


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (apt install chromium)")
def test_chromium_renders_the_report_images(tmp_path):
    out = _run(tmp_path)
    shot = tmp_path / "shot.png"
    proc = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                           "--disable-background-networking", "--hide-scrollbars",
                           "--no-first-run", "--disable-component-update", "--disable-sync",
                           f"--user-data-dir={tmp_path / 'chromium-profile'}",
                           "--window-size=1200,2400", f"--screenshot={shot}",
                           (out / "report.html").as_uri()],
                          capture_output=True, timeout=120)
    assert shot.exists(), proc.stderr.decode(errors="replace")[-500:]
    from matplotlib.image import imread
    img = (imread(str(shot))[:, :, :3] * 255).round()
    # the figure's joint-1 line is matplotlib's C0 blue: only a rendered PNG figure has it
    blue = np.all(np.abs(img - [31, 119, 180]) <= 12, axis=2).sum()
    # the diagram's (SVG) box headers are the pale orange of output ports
    orange = np.all(np.abs(img - [253, 242, 233]) <= 3, axis=2).sum()
    assert blue > 200 and orange > 50, (blue, orange)



def test_the_diagram_is_shown_whole_at_the_page_width_and_opens_full_size(tmp_path):
    out = _run(tmp_path)
    text = (out / "report.html").read_text()
    page = _parse(out / "report.html")
    diagram = [img for img in page.images if img["alt"] == "block diagram"]
    assert len(diagram) == 1 and "onclick" in diagram[0]
    style = text.split("<style>", 1)[1].split("</style>", 1)[0]
    assert "max-height" not in style and "overflow" not in style      # no scroll box


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (apt install chromium)")
def test_chromium_shows_the_whole_diagram_and_a_click_opens_it(tmp_path):
    out = tmp_path / "run"                      # a picture wider and taller than the window
    assert main(["run", "diagrams/theorem6.yaml", "-o", str(out), "-q", "--no-plots",
                 "--set", "simulation.t_final=0.01", "--report"]) == 0
    probe = """<script>
    window.open = function (url) {
      fetch(url).then(r => r.text()).then(t => document.body.setAttribute(
        "data-opened", url.slice(0, 5) + " " + (t.indexOf("<svg") >= 0)));
    };
    window.addEventListener("load", function () {
      var img = document.querySelector("img[alt='block diagram']"), box = img.getBoundingClientRect();
      var clipped = false;
      for (var el = img.parentElement; el; el = el.parentElement)
        clipped = clipped || el.scrollHeight > el.clientHeight + 1 && el !== document.documentElement
                  && el !== document.body;
      document.body.setAttribute("data-size", [Math.round(box.width), Math.round(box.height),
        img.naturalWidth, img.naturalHeight, img.parentElement.clientWidth, clipped].join(" "));
      img.click();
    });
    </script>"""
    page = out / "probe.html"
    page.write_text((out / "report.html").read_text().replace("</body>", probe + "</body>"))
    proc = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                           f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1200,2400",
                           "--virtual-time-budget=5000", "--dump-dom", page.as_uri()],
                          capture_output=True, timeout=120)
    dom = proc.stdout.decode(errors="replace")
    import re
    size = re.search(r'data-size="([^"]*)"', dom)
    assert size, proc.stderr.decode(errors="replace")[-500:]
    width, height, natural_w, natural_h, room, clipped = size.group(1).split()
    assert clipped == "false"
    # shown whole: scaled to the page's width, its aspect ratio kept
    assert int(natural_w) > int(room) and abs(int(width) - int(room)) <= 1
    assert abs(int(height) / int(width) - int(natural_h) / int(natural_w)) < 0.02
    assert re.search(r'data-opened="blob: true"', dom)                 # the click opens it


STOPPED = """
description: x' = -1 from 1.234 until x reaches 0 (a Stop); a Saturation at 0.5 on the way
blocks:
  one:  {type: Constant, value: -1.0}
  x:    {type: Integrator, initial: 1.234}
  sat:  {type: Saturation, lower: -0.5, upper: 0.5}
  stop: {type: Stop}
connections:
  - one.y -> x.u
  - x.y -> sat.u
  - x.y -> stop.u
simulation: {t_final: 5.0, step: 0.1, solver: rk4}
"""


def test_state_events_are_saved_read_back_and_on_the_page(tmp_path, capsys):
    """The located crossings (x = 0.5 at t = 0.734, the Stop at t = 1.234) are in
    summary.json, come back from load_result as the run's own events, are said in the
    run's summary line and listed on the report page."""
    import fwdstep
    path = tmp_path / "stop.yaml"
    path.write_text(STOPPED)
    fresh = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    assert main(["run", str(path), "-o", str(tmp_path / "out"), "--report"]) == 0
    line = capsys.readouterr().out
    assert "stopped: t = 1.234 s" in line
    assert "2 state events located (first: t = 0.734 s, block 'sat' upper falling)" in line
    back = fwdstep.load_result(str(tmp_path / "out"))
    assert back.events == fresh.events
    assert [(e.block, e.kind) for e in back.events] == [("sat", "upper falling"),
                                                        ("stop", "u falling")]
    np.testing.assert_allclose([e.time for e in back.events], [0.734, 1.234], atol=1e-12)
    page = _Page()
    page.feed((tmp_path / "out" / "report.html").read_text())
    text = " ".join(page.text)
    assert "State events" in text and "upper falling" in text and "u falling" in text


def test_a_hand_edited_event_is_refused_in_one_line(tmp_path):
    import json
    import fwdstep
    from fwdstep.core.errors import DamagedFileError
    path = tmp_path / "stop.yaml"
    path.write_text(STOPPED)
    assert main(["run", str(path), "-o", str(tmp_path / "out"), "--no-plots", "-q"]) == 0
    summ = tmp_path / "out" / "summary.json"
    s = json.loads(summ.read_text())
    s["events"][1]["time"] = "soon"
    summ.write_text(json.dumps(s))
    with pytest.raises(DamagedFileError, match="event 2 is not a mapping of time"):
        fwdstep.load_result(str(tmp_path / "out"))
