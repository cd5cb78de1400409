"""defects.csv cells that a spreadsheet could run as formulas are neutralised."""

import csv
import io

import pytest

from server.reports.fields import DEFECT_FIELDS
from server.reports.tables import defects_csv


def _comment_cell(comment: str) -> str:
    record = dict.fromkeys(DEFECT_FIELDS, None) | {"comment": comment}
    text = "".join(defects_csv([record])).lstrip("\ufeff")
    return next(csv.DictReader(io.StringIO(text)))["comment"]


@pytest.mark.parametrize(
    "comment",
    [
        "=1+1",
        "+cmd",
        "-2",
        "@SUM(A1)",
        " =HYPERLINK(x)",
        "\n=1",
        "\t=1",
        "＝1+1",
        "|calc",
        "%0A",
        "　＝x",
        "\u200b=1+1",
        "\ufeff=1+1",
        "\u200b\u200bcmd",
        "\u2060@SUM(A1)",
    ],
)
def test_formula_like_comments_are_quoted(comment: str) -> None:
    assert _comment_cell(comment) == "'" + comment


@pytest.mark.parametrize("comment", ["crack at weld toe", "2 mm wide", "Riß", ""])
def test_plain_comments_pass_unchanged(comment: str) -> None:
    assert _comment_cell(comment) == comment


def test_the_mcap_defect_record_has_the_rest_apis_fields() -> None:
    from server.api.schemas import DefectPublic
    from server.reports.fields import RECORD_FIELDS

    assert set(RECORD_FIELDS) == set(DefectPublic.model_fields)
