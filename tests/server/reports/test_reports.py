"""Reports and exports of a real inspection: the simulated robot streams a session to the real
server, the pipeline processes it, then report.json, the PDF (rendered to PNG pages), the CSV,
defect review, thumbnails and the MCAP log (read back with the mcap library, re-imported)."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
import pypdfium2
import pytest
from mcap.reader import make_reader

from tests.conftest import LiveServer
from tests.server.helpers import empty_session, wait_job


def test_report_json_summarises_the_session(inspected: tuple[LiveServer, str]) -> None:
    live, sid = inspected
    report = httpx.get(f"{live.url}/api/sessions/{sid}/report.json").raise_for_status().json()
    assert (
        report["cover"]["structure"]
        and report["cover"]["location"]
        and report["cover"]["operator"] == "demo"
    )
    s = report["summary"]
    assert s["frames"] > 20 and s["clouds"] > 5
    assert 0.1 < s["area_covered_m2"] < 2.0 and 1.0 < s["distance_travelled_m"] < 20.0
    assert report["missing"] == [] and report["defect_source"] == "mosaic"
    assert s["defects"] == len(report["defects"]) > 0
    assert sum(s["defects_by_class"].values()) == s["defects"]
    assert all(d["length_mm"] and d["world_x_m"] is not None for d in report["defects"])
    assert [d["number"] for d in report["defects"]] == list(range(1, s["defects"] + 1))
    assert set(report["parameters"]) == {"stitch", "map", "detect"}
    # coverage: the simulated lanes overlap, so nearly all the surface in view counts
    cov = report["coverage"]
    assert 0.9 < cov["fraction_imaged"] <= 1.0 and cov["frames_not_counted"] == 0
    assert cov["area_surface_m2"] == pytest.approx(s["area_covered_m2"], rel=0.25)


def test_review_is_stored_and_shown_in_csv_and_pdf(inspected: tuple[LiveServer, str]) -> None:
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    defects = httpx.get(f"{api}/defects", params={"source": "mosaic"}).json()["data"]
    first, second = defects[0]["id"], defects[1]["id"]
    r = httpx.patch(
        f"{api}/defects/{first}",
        json={
            "review_status": "confirmed",
            "condition_state": "CS3",
            "comment": '=HYPERLINK("x") Riß at weld toe, re-inspect',
        },
    )
    assert r.status_code == 200 and r.json()["condition_state"] == "CS3" and r.json()["reviewed_by"]
    assert (
        httpx.patch(f"{api}/defects/{second}", json={"review_status": "rejected"}).status_code
        == 200
    )
    assert httpx.patch(f"{api}/defects/{first}", json={"condition_state": "CS9"}).status_code == 422
    assert (
        httpx.patch(f"{api}/defects/999999", json={"review_status": "confirmed"}).status_code == 404
    )
    third = defects[2]["id"]  # reviewed, then taken back entirely: it names nobody
    httpx.patch(f"{api}/defects/{third}", json={"review_status": "confirmed"}).raise_for_status()
    reset = httpx.patch(f"{api}/defects/{third}", json={"review_status": "unreviewed"}).json()
    assert reset["reviewed_by"] is None and reset["reviewed_at"] is None
    confirmed = httpx.get(f"{api}/defects", params={"review_status": "confirmed"}).json()
    assert [d["id"] for d in confirmed["data"]] == [first]
    by_length = httpx.get(
        f"{api}/defects", params={"source": "mosaic", "sort": "-length_mm"}
    ).json()["data"]
    lengths = [d["length_mm"] for d in by_length]
    assert lengths == sorted(lengths, reverse=True)

    raw = httpx.get(f"{api}/defects.csv")
    assert raw.status_code == 200 and raw.headers["content-type"].startswith("text/csv")
    assert "attachment" in raw.headers["content-disposition"]
    rows = list(csv.DictReader(io.StringIO(raw.content.decode("utf-8-sig"))))
    assert len(rows) == len(defects)
    row = next(r for r in rows if int(r["id"]) == first)
    assert row["condition_state"] == "CS3" and row["review_status"] == "confirmed"
    # no formula injection, accents intact
    assert row["comment"].startswith("'=HYPERLINK") and "Riß" in row["comment"]
    assert float(row["length_mm"]) > 0

    report = httpx.get(f"{api}/report.json").json()
    assert report["summary"]["defects_by_condition_state"]["CS3"] == 1
    assert report["summary"]["defects_rejected"] == 1

    pdf = httpx.get(f"{api}/report.pdf", timeout=120)
    assert pdf.status_code == 200 and pdf.headers["content-type"] == "application/pdf"
    doc = pypdfium2.PdfDocument(pdf.content)
    assert len(doc) >= 5
    text = " ".join(
        " ".join(doc[i].get_textpage().get_text_range() for i in range(len(doc))).split()
    )
    for expected in (
        "Steel structure inspection report",
        report["cover"]["structure"],
        "Summary",
        "Defects",
        "3D map of the structure",
        "Appendix — processing parameters",
        "Coverage",
        "mm/px, sharp and exposed",
        "CS3",
        "Riß at weld toe",
        "confirmed",
    ):
        assert expected in text, expected
    assert "No mosaic: No mosaic" not in text and "Duration 0 s" not in text
    assert "by anonymous" in text  # the reviewer's name on one line
    assert "Steel structure inspection report" in doc[0].get_textpage().get_text_range()
    cover = list(doc[0].get_objects())  # no mosaic picture on the cover: it has its own page
    assert not any(o.type == pypdfium2.raw.FPDF_PAGEOBJ_IMAGE for o in cover)
    assert any(o.type == pypdfium2.raw.FPDF_PAGEOBJ_IMAGE for o in doc[2].get_objects())
    # one number per defect everywhere: the API's, the PDF's and the CSV's
    numbers = {d["id"]: d["number"] for d in defects}
    assert sorted(numbers.values()) == list(range(1, len(defects) + 1))
    assert {int(r["id"]): int(r["number"]) for r in rows} == numbers
    assert all(d["number"] == numbers[d["id"]] for d in report["defects"])
    for i in range(len(doc)):  # every page renders and has something on it
        page = np.asarray(doc[i].render(scale=0.5).to_pil().convert("L"))
        assert page.shape[0] > page.shape[1] > 200  # A4 portrait
        assert (page < 200).mean() > 0.005, f"page {i + 1} is blank"
    mosaic_page = np.asarray(doc[2].render(scale=1.0).to_pil().convert("RGB"))
    red = (mosaic_page[..., 0] > 180) & (mosaic_page[..., 1] < 80) & (mosaic_page[..., 2] < 80)
    assert red.sum() > 50  # the numbered defect markers are drawn
    doc.close()


def test_rerunning_detection_keeps_the_reviews(inspected: tuple[LiveServer, str]) -> None:
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    d = httpx.get(
        f"{api}/defects", params={"source": "mosaic", "sort": "-length_mm", "limit": 1}
    ).json()["data"][0]
    httpx.patch(
        f"{api}/defects/{d['id']}",
        json={"review_status": "confirmed", "condition_state": "CS2", "comment": "kept"},
    ).raise_for_status()
    job = wait_job(live.url, httpx.post(f"{api}/jobs", json={"kind": "detect"}).json()["id"])
    assert job["state"] == "done" and job["result"]["reviews_carried_over"] >= 1
    again = [
        x
        for x in httpx.get(f"{api}/defects", params={"source": "mosaic"}).json()["data"]
        if (x["bbox_x"], x["bbox_y"]) == (d["bbox_x"], d["bbox_y"])
    ]
    assert again  # the same defect found again (a new row; SQLite may reuse the id)
    assert (again[0]["review_status"], again[0]["condition_state"], again[0]["comment"]) == (
        "confirmed",
        "CS2",
        "kept",
    )


def test_defect_thumbnail_and_cloud_downloads(inspected: tuple[LiveServer, str]) -> None:
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    for source in ("mosaic", "frame"):
        d = httpx.get(f"{api}/defects", params={"source": source, "limit": 1}).json()["data"][0]
        r = httpx.get(f"{api}/defects/{d['id']}/thumbnail.jpg", params={"size": 128})
        assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
        img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
        assert max(img.shape[:2]) == 128 and img.std() > 5
    clouds = httpx.get(f"{api}/clouds", params={"limit": 2}).json()
    assert clouds["count"] > 5 and len(clouds["data"]) == 2
    seq = clouds["data"][0]["seq"]
    ply = httpx.get(f"{api}/clouds/{seq}/points.ply")
    assert ply.status_code == 200 and ply.content.startswith(b"ply\nformat binary_little_endian")
    n = int(ply.content.split(b"element vertex ")[1].split(b"\n")[0])
    assert n > 1000 and len(ply.content.split(b"end_header\n", 1)[1]) == 12 * n
    assert httpx.get(f"{api}/clouds/{seq}/raw").status_code == 200
    assert httpx.get(f"{api}/clouds/99999999/raw").status_code == 404


def test_mcap_opens_with_foxglove_schemas_and_reimports_losslessly(
    inspected: tuple[LiveServer, str], tmp_path: Path
) -> None:
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    path = tmp_path / "session.mcap"
    first = httpx.get(f"{api}/export.mcap", timeout=60)
    if first.status_code == 202:  # out of date (detection ran again): it is made again first
        assert wait_job(live.url, first.json()["id"])["state"] == "done"
    with httpx.stream("GET", f"{api}/export.mcap", timeout=60) as r:
        assert r.status_code == 200
        with path.open("wb") as fh:
            for chunk in r.iter_bytes():
                fh.write(chunk)
    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        counts = {
            summary.channels[cid].topic: n
            for cid, n in summary.statistics.channel_message_counts.items()
        }
    assert schemas["/camera/image"] == "foxglove.CompressedImage"
    assert (
        schemas["/tof/points"] == "foxglove.PointCloud"
        and schemas["/tf"] == "foxglove.FrameTransform"
    )
    assert (
        schemas["/camera/odometry"] == "foxglove.PoseInFrame"
        and schemas["/map/points"] == "foxglove.PointCloud"
    )
    assert schemas["/inspection/defect_markers"] == "foxglove.SceneUpdate"
    session = httpx.get(api).json()
    assert (
        counts["/camera/image"] == session["frames"] and counts["/tof/points"] == session["clouds"]
    )
    assert counts["/robot/telemetry"] == session["telemetry"]

    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "server.cli",
            "import",
            str(path),
            "--data-dir",
            str(live.settings.data_dir),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "STEELSCAN_DATABASE_URL": live.settings.resolved_database_url()},
    )
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    new = result["session_id"]
    assert (
        new != sid
        and result["frames"] == session["frames"]
        and result["clouds"] == session["clouds"]
    )
    copy = httpx.get(f"{live.url}/api/sessions/{new}").json()
    # processed as a session that ends, and told apart from the original
    kinds = {j["kind"] for j in copy["jobs"]}
    assert len(result["jobs"]) == len(kinds) and {"stitch", "detect", "map"} <= kinds
    assert copy["imported"] and not session["imported"]
    assert (
        copy["structure"] == session["structure"] and copy["calibration"] == session["calibration"]
    )
    a = httpx.get(f"{api}/frames", params={"limit": 1000}).json()["data"]
    b = httpx.get(f"{live.url}/api/sessions/{new}/frames", params={"limit": 1000}).json()["data"]
    assert a == b  # sequence numbers, timestamps, sizes and odometry poses
    for f in a[:: max(1, len(a) // 8)]:
        assert (
            httpx.get(f"{api}/frames/{f['seq']}/image").content
            == httpx.get(f"{live.url}/api/sessions/{new}/frames/{f['seq']}/image").content
        )
    with path.open("rb") as fh:  # the same through REST
        up = httpx.post(
            f"{live.url}/api/sessions/import", files={"file": ("session.mcap", fh)}, timeout=120
        )
    assert (
        up.status_code == 201
        and up.json()["frames"] == session["frames"]
        and up.json()["session_id"] not in (sid, new)
    )
    jobs = httpx.get(f"{live.url}/api/sessions/{up.json()['session_id']}/jobs").json()
    assert sorted(j["id"] for j in jobs) == sorted(up.json()["jobs"])
    bad = httpx.post(
        f"{live.url}/api/sessions/import", files={"file": ("x.mcap", b"not an mcap at all")}
    )
    assert bad.status_code == 422 and "x.mcap" in bad.json()["detail"]
    ca = httpx.get(f"{api}/clouds", params={"limit": 1000}).json()["data"]
    cb = httpx.get(f"{live.url}/api/sessions/{new}/clouds", params={"limit": 1000}).json()["data"]
    assert ca == cb
    for c in ca[:: max(1, len(ca) // 5)]:
        assert (
            httpx.get(f"{api}/clouds/{c['seq']}/raw").content
            == httpx.get(f"{live.url}/api/sessions/{new}/clouds/{c['seq']}/raw").content
        )


def test_report_of_an_empty_session_says_what_is_missing(live_server: LiveServer) -> None:
    sid = empty_session(live_server)
    api = f"{live_server.url}/api/sessions/{sid}"
    report = httpx.get(f"{api}/report.json").json()
    assert report["summary"]["frames"] == 0 and report["defects"] == []
    assert report["missing"] == ["stitch", "map", "detect"]
    assert any("No mosaic" in n and "not been run" in n for n in report["notes"])
    pdf = httpx.get(f"{api}/report.pdf", timeout=60)
    assert pdf.status_code == 200
    doc = pypdfium2.PdfDocument(pdf.content)
    text = "\n".join(doc[i].get_textpage().get_text_range() for i in range(len(doc)))
    assert "No mosaic" in text and "Defect detection has not run" in text and "No 3D map" in text
    doc.close()
    rows = httpx.get(f"{api}/defects.csv").content.decode("utf-8-sig").splitlines()
    assert len(rows) == 1 and rows[0].startswith("number,id,defect_class")
    assert httpx.get(f"{live_server.url}/api/sessions/nope/report.pdf").status_code == 404
    # a session that is still live gets an export job, not a stale file
    r = httpx.get(f"{api}/export.mcap")
    assert r.status_code == 202 and r.json()["kind"] == "export"
    job = wait_job(live_server.url, r.json()["id"])
    assert job["state"] == "done", job


def test_session_cover_fields_can_be_corrected(live_server: LiveServer) -> None:
    sid = empty_session(live_server)
    api = f"{live_server.url}/api/sessions/{sid}"
    r = httpx.patch(api, json={"location": "Bridge 12, pier 3 east", "notes": "wind 8 m/s"})
    assert r.status_code == 200 and r.json()["location"] == "Bridge 12, pier 3 east"
    assert httpx.patch(api, json={"structure": ""}).status_code == 422
    assert httpx.patch(api, json={"robot_id": 3}).status_code == 422
    lone_surrogate = b'{"notes": "wind \\ud800"}'  # valid JSON, not storable as UTF-8
    headers = {"content-type": "application/json"}
    assert httpx.patch(api, content=lone_surrogate, headers=headers).status_code == 422
    assert httpx.get(f"{api}/report.json").json()["cover"]["notes"] == "wind 8 m/s"


def test_detect_job_method_is_chosen_per_job_and_reviews_carry_over(
    inspected: tuple[LiveServer, str],
) -> None:
    """The station detected with its default, the shipped network; a detect job asked for
    ``proposed`` uses the filter pipeline; both find the simulated cracks."""
    live, sid = inspected
    url = live.url
    mosaic = {"source": "mosaic", "limit": 500}
    jobs = httpx.get(f"{url}/api/sessions/{sid}/jobs").json()
    default = next(j for j in jobs if j["kind"] == "detect")["result"]
    assert default["method"] == "learned" and default["params"]["crack"]["threshold"] > 0
    first = httpx.get(f"{url}/api/sessions/{sid}/defects", params=mosaic).json()["data"]
    crack = max((d for d in first if d["defect_class"] == "crack"), key=lambda d: d["length_px"])
    httpx.patch(
        f"{url}/api/sessions/{sid}/defects/{crack['id']}", json={"review_status": "confirmed"}
    ).raise_for_status()
    bad = httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": "map", "method": "learned"})
    assert bad.status_code == 422
    job = httpx.post(
        f"{url}/api/sessions/{sid}/jobs", json={"kind": "detect", "method": "proposed"}
    ).json()
    deadline = time.monotonic() + 240
    while job["state"] not in ("done", "failed"):
        assert time.monotonic() < deadline
        time.sleep(0.3)
        job = httpx.get(f"{url}/api/jobs/{job['id']}").json()
    assert job["state"] == "done", job
    assert job["result"]["method"] == "proposed"
    assert job["result"]["reviews_carried_over"] >= 1
    from processing.metrics import Box, match_defects
    from robot_link.sim.structure import make_structure
    from server.cli.demo import world_boxes

    truth = [Box(d.defect_class, *d.bbox_m) for d in make_structure(11).defects]
    again = httpx.get(f"{url}/api/sessions/{sid}/defects", params=mosaic).json()["data"]
    by_network = match_defects(world_boxes(first), truth)
    by_proposed = match_defects(world_boxes(again), truth)
    assert by_proposed >= 1 and by_network >= max(1, by_proposed - 1), (by_network, by_proposed)
    # the shared session back as the station left it: its defects by the network
    job = httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": "detect"}).json()
    deadline = time.monotonic() + 240
    while job["state"] not in ("done", "failed"):
        assert time.monotonic() < deadline
        time.sleep(0.3)
        job = httpx.get(f"{url}/api/jobs/{job['id']}").json()
    assert job["state"] == "done" and job["result"]["method"] == "learned", job


def test_the_pdf_takes_any_comment_the_api_accepts(inspected: tuple[LiveServer, str]) -> None:
    """Comments of many lines or one endless word (up to the 2,000 characters allowed)
    are cut short in the defect table and printed in full after it."""
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    defects = httpx.get(f"{api}/defects", params={"source": "mosaic"}).json()["data"]
    defects = [d for d in defects if d["review_status"] != "rejected"]  # listed in the PDF
    lines = "\n".join(f"line {i} of the note" for i in range(90))[:2000]
    word = "W" * 1999 + "!"
    for d, comment in zip(defects[-2:], (lines, word)):
        r = httpx.patch(f"{api}/defects/{d['id']}", json={"comment": comment})
        assert r.status_code == 200
    pdf = httpx.get(f"{api}/report.pdf", timeout=120)
    assert pdf.status_code == 200, pdf.text[:300]
    doc = pypdfium2.PdfDocument(pdf.content)
    text = "".join(doc[i].get_textpage().get_text_range() for i in range(len(doc)))
    doc.close()
    squeezed = "".join(text.split())
    assert "Commentsinfull" in squeezed and "line89ofthenote" in squeezed
    runs = [len(r) for r in re.findall("W+", squeezed)]  # the full text may cross a page
    assert 30 in runs and sum(runs) == 30 + 1999, runs
