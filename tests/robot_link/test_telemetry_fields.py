"""The telemetry's numeric fields and the units their keys name, on the simulated robot's
own samples."""

from __future__ import annotations

from robot_link.sim.inspection import InspectionSim, SimConfig
from robot_link.telemetry_fields import field_unit, key_unit, numeric_fields


class _NoLink:
    """The simulator's link, never used: only its counters are read."""

    pending = 0
    session_id = "00000000-0000-0000-0000-000000000001"

    class stats:  # noqa: N801
        resent = 0
        last_ack_latency_s = 0.004
        reconnects = 0
        video_dropped = 0


def test_a_simulated_sample_flattens_to_its_quantities_with_units() -> None:
    sim = InspectionSim(_NoLink(), SimConfig(seed=3, lanes=1, time_scale=0.0))  # type: ignore[arg-type]
    sample = sim.telemetry_meta()
    fields = numeric_fields(sample)
    assert fields["battery_v.main"] == sample["battery_v"]["main"]
    assert fields["wheel_speed_mps[3]"] == sample["wheel_speed_mps"][3]
    assert fields["pose.yaw"] == sample["pose"]["yaw"]
    assert fields["link.ack_latency_ms"] == 4.0
    assert "edge_action" not in fields and "paused" not in fields  # words and flags
    assert not any(k.startswith("ir_no_surface") for k in fields)
    units = {k: field_unit(k) for k in fields}
    assert units["battery_v.logic"] == "V"
    assert units["wheel_speed_mps[0]"] == "m/s"
    assert units["wheel_distance_m[2]"] == "m"
    assert units["ir_range_m[1]"] == "m"
    assert units["pose.x"] == "m" and units["pose.yaw"] == "rad"
    assert units["inclination_deg"] == "°"
    assert units["distance_m"] == "m"
    assert units["link.ack_latency_ms"] == "ms"
    assert units["adhesion_margin"] == "" and units["link.resent"] == ""


def test_the_longest_suffix_names_the_unit() -> None:
    assert key_unit("angular_radps") == "rad/s"  # not "_s"
    assert key_unit("linear_mps") == "m/s"
    assert key_unit("hold_ms") == "ms"
    assert key_unit("temperature_c") == "°C"
    assert key_unit("cpu_percent") == "%"
    assert key_unit("_m") == ""  # a suffix alone names no quantity
    assert field_unit("onboard.camera_hz") == "Hz"
    assert field_unit("motor_current_a[1]") == "A"


def test_non_finite_and_deep_values_are_left_out() -> None:
    deep: dict = {"v": 1.0}
    for _ in range(10):
        deep = {"d": deep}
    fields = numeric_fields({"a_m": float("nan"), "b_m": float("inf"), "c_m": 2, "deep": deep})
    assert fields == {"c_m": 2.0}
