"""The REST API fuzzed against its own OpenAPI schema (schemathesis): no request, however
odd, makes the station answer with a server error."""

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error

from tests.conftest import LiveServer

pytestmark = pytest.mark.slow  # an end-to-end run


def test_no_request_makes_a_server_error(live_server: LiveServer) -> None:
    schema = schemathesis.openapi.from_url(f"{live_server.url}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 10
    for operation in operations:

        @given(operation.as_strategy())
        @settings(
            max_examples=12, deadline=None, suppress_health_check=list(HealthCheck), database=None
        )
        def fuzz(case: schemathesis.Case) -> None:
            # one connection per request: a kept-alive one the station closes as idle while
            # the next example is being generated would read as a dropped connection
            case.call_and_validate(checks=[not_a_server_error], headers={"Connection": "close"})

        fuzz()
