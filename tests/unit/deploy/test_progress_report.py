"""`zenpilot fly`'s progress line and report.html."""

import html.parser
import io

import schemas
from deploy import progress as progress_mod
from deploy.progress import FlightProgress
from deploy.report import RUN_FILES, write_report

ITEMS = ({"type": "takeoff", "altitude_m": 1.0}, {"type": "hold", "settle_s": 2.0, "duration_s": 8.0},
         {"type": "land"})


class _Session:
    def declare_subscriber(self, key, callback):
        self.key, self.callback = key, callback
        return self

    def undeclare(self):
        pass


class _Sample:
    def __init__(self, payload):
        self.payload = self

        def to_bytes():
            return payload
        self.to_bytes = to_bytes


def setpoint(t, item, state="running", phase="hold"):
    return _Sample(schemas.PLANNER_SETPOINT.encode(t, int(t * 50), "planner", {
        "mode": "position", "armed": True, "position_m": [0.0, 0.0, 1.0], "attitude_rad": [0.0, 0.0, 0.0],
        "item": item, "phase": phase, "measure": False, "mission_state": state}))


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_progress_shows_sim_time_speed_and_the_mission_bar():
    session, out = _Session(), _Tty()
    p = FlightProgress(session, 0, ITEMS, out)
    assert session.key == "zp/0/planner/setpoint" and p.line() is None   # nothing heard yet
    session.callback(setpoint(3.0, 1))
    p.show()   # the poll sees item 2 begin
    session.callback(setpoint(8.0, 1))   # 5 s into the 10 s hold: item 2 of 3, half done
    line = p.line()
    assert "sim    8.0 s" in line and "x" in line and "item 2/3 hold" in line
    assert " 50 %" in line and "[############------------]" in line
    assert out.getvalue().startswith("\r\033[K")   # in place on a terminal
    session.callback(setpoint(20.0, 2, "completed", "landed"))
    assert "100 %" in p.line() and "mission completed" in p.line()
    p.close()
    assert out.getvalue().endswith("\n")


def test_progress_without_a_terminal_prints_plain_lines_now_and_then(monkeypatch):
    session, out = _Session(), io.StringIO()
    monkeypatch.setattr(progress_mod, "PLAIN_EVERY_S", 0.0)
    p = FlightProgress(session, 0, ITEMS, out)
    session.callback(setpoint(1.0, 0, phase="climb"))
    p.show()
    p.show()
    lines = out.getvalue().splitlines()
    assert len(lines) == 2 and "\r" not in out.getvalue() and "item 1/3 takeoff (climb)" in lines[0]


class _Parser(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.text = [], []

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.images.append(dict(attrs)["src"])

    def handle_data(self, data):
        self.text.append(data)


def test_report_is_one_page_with_plots_metrics_mission_and_stack(tmp_path):
    png = tmp_path / "position.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\nnot really an image")
    (tmp_path / RUN_FILES["mission"]).write_text('[mission]\nname = "hover" # <b>\n')
    (tmp_path / RUN_FILES["stack"]).write_text("[stack]\nvehicle_id = 0\n")
    metrics = {"mission": "hover", "vehicle": "x250", "mode": "lockstep", "seed": 0, "duration_s": 18.8,
               "completed": True, "crashed": False, "position_rms_m": 0.002}
    path = write_report(tmp_path, metrics, "position_rms_m  0.002", [png], "")
    page = path.read_text()
    parser = _Parser()
    parser.feed(page)
    text = "".join(parser.text)
    assert parser.images == ["data:image/png;base64,iVBORw0KGgpub3QgcmVhbGx5IGFuIGltYWdl"]   # inlined: one file
    assert 'name = "hover" # <b>' in text and "vehicle_id = 0" in text and "position_rms_m  0.002" in text
    assert "<b>" not in page   # the files' text is escaped, not markup
    assert "Not recorded with this flight (command.txt)" in text
    assert '"seed": 0' in text   # metrics.json too
