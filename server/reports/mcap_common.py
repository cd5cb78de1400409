"""What the MCAP export and import share: the metadata record's name, the JSON schema."""

from __future__ import annotations

import json
from collections.abc import Callable

METADATA = "steelscan.session"  # the metadata record with the session's cover and calibration
JSON_SCHEMA = json.dumps({"type": "object"}).encode()
Progress = Callable[[float, str], None]
