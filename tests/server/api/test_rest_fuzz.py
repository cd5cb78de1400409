"""The REST API fuzzed against its own OpenAPI schema (schemathesis): no request, however
odd, makes the station answer with a server error."""

import time

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error

from server.link.guard import NEW_PER_S
from tests.conftest import LiveServer

pytestmark = pytest.mark.slow  # an end-to-end run


def test_no_request_makes_a_server_error(live_server: LiveServer) -> None:
    schema = schemathesis.openapi.from_url(f"{live_server.url}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 10
    # one new connection a request, below the rate at which the station's flood guard
    # closes an address's new connections unanswered
    interval = 1.25 / NEW_PER_S
    last = [0.0]
    for operation in operations:

        @given(operation.as_strategy())
        @settings(
            max_examples=12, deadline=None, suppress_health_check=list(HealthCheck), database=None
        )
        def fuzz(case: schemathesis.Case) -> None:
            # one connection per request: a kept-alive one the station closes as idle while
            # the next example is being generated would read as a dropped connection
            time.sleep(max(0.0, last[0] + interval - time.monotonic()))
            last[0] = time.monotonic()
            case.call_and_validate(checks=[not_a_server_error], headers={"Connection": "close"})

        fuzz()
