"""frontend/encoders.py: interpolation to image stamps, bad samples, bounded memory."""

import math

import pytest

from ptz_selfcal.frontend.encoders import EncoderConfig, EncoderInterpolator, QueryStatus, Rejection


def feed(
    enc: EncoderInterpolator,
    times,
    pan=lambda t: 0.1 * t,
    tilt=lambda t: -0.05 * t,
    zoom=lambda t: 100 + 10 * t,
):
    for t in times:
        assert enc.add(t, {"pan": pan(t), "tilt": tilt(t), "zoom": zoom(t)}) == []


def test_linear_interpolation_between_samples():
    enc = EncoderInterpolator()
    feed(enc, [0.0, 0.1, 0.2, 0.3])
    q = enc.query(0.125)
    assert q.valid and q.status is QueryStatus.VALID
    assert (
        q.pan == pytest.approx(0.0125)
        and q.tilt == pytest.approx(-0.00625)
        and q.zoom == pytest.approx(101.25)
    )


def test_time_offset_shifts_encoder_stamps_onto_the_image_clock():
    enc = EncoderInterpolator(EncoderConfig(time_offset=-0.05))  # encoders stamped 50 ms late
    feed(enc, [0.05, 0.15, 0.25])
    assert enc.query(0.1).pan == pytest.approx(0.1 * 0.15)


def test_just_past_the_newest_sample_a_moving_joint_is_extrapolated_not_held():
    # a zooming head sampled at 15 Hz: a frame 40 ms past the newest sample gets the zoom of its own time
    enc = EncoderInterpolator(EncoderConfig(max_gap=0.5, max_hold=0.05))
    feed(enc, [0.0, 1 / 15, 2 / 15], zoom=lambda t: 1000.0 + 3000.0 * t)
    q = enc.query(2 / 15 + 0.04)
    assert q.valid and q.zoom == pytest.approx(1000.0 + 3000.0 * (2 / 15 + 0.04))
    # the last two samples too far apart to say how the joint moves: the newest value is held
    enc = EncoderInterpolator(EncoderConfig(max_gap=0.5, max_hold=0.05))
    feed(enc, [0.0, 1.0], zoom=lambda t: 1000.0 + 3000.0 * t)
    assert enc.query(1.04).zoom == pytest.approx(4000.0)
    # pan along the shorter arc across +-pi
    enc = EncoderInterpolator()
    feed(enc, [0.0, 0.1], pan=lambda t: math.pi - 0.05 + t)
    pan = enc.query(0.14).pan
    assert abs(math.remainder(pan - (math.pi + 0.09), 2 * math.pi)) < 1e-9


def test_pan_interpolates_along_the_shorter_arc():
    enc = EncoderInterpolator()
    enc.add(0.0, {"pan": math.pi - 0.1, "tilt": 0.0, "zoom": 0.0})
    enc.add(0.1, {"pan": -math.pi + 0.1, "tilt": 0.0, "zoom": 0.0})
    pan = enc.query(0.05).pan
    assert abs(math.remainder(pan - math.pi, 2 * math.pi)) < 1e-9


def test_nan_inf_samples_rejected_and_counted():
    enc = EncoderInterpolator()
    feed(enc, [0.0, 0.2])
    rejected = enc.add(0.1, {"pan": float("nan"), "tilt": 0.0, "zoom": float("inf")})
    assert sorted(rejected) == [("pan", Rejection.NOT_FINITE), ("zoom", Rejection.NOT_FINITE)]
    assert enc.add(float("nan"), {"pan": 0.0, "tilt": 0.0, "zoom": 0.0})[0][1] is Rejection.NOT_FINITE
    assert enc.rejections["not_finite"] == 5
    # the NaN never reaches an interpolated value; tilt of the partial sample was stored
    q = enc.query(0.1)
    assert q.valid and math.isfinite(q.pan) and q.pan == pytest.approx(0.01)


def test_out_of_order_samples_are_inserted_and_duplicates_rejected():
    enc = EncoderInterpolator()
    feed(enc, [0.0, 0.3, 0.1, 0.2])  # 0.1 and 0.2 arrive late
    assert enc.query(0.15).pan == pytest.approx(0.015)
    assert enc.add(0.1, {"pan": 5.0, "tilt": 5.0, "zoom": 5.0}) == [
        ("pan", Rejection.DUPLICATE), ("tilt", Rejection.DUPLICATE), ("zoom", Rejection.DUPLICATE)
    ]  # fmt: skip
    assert enc.query(0.1).pan == pytest.approx(0.01)


def test_validity_states():
    enc = EncoderInterpolator(EncoderConfig(max_gap=0.5, max_hold=0.05))
    assert enc.query(1.0).status is QueryStatus.NO_DATA
    feed(enc, [1.0, 1.2, 3.0, 3.1])
    assert enc.query(2.0).status is QueryStatus.GAP  # bracketed by samples 1.8 s apart
    assert enc.query(1.22).valid  # held: within max_hold of 1.2
    assert enc.query(3.12).valid and enc.query(3.12).pan == pytest.approx(0.312)  # extrapolated
    assert enc.query(3.5).status is QueryStatus.NOT_YET
    assert enc.query(0.5).status is QueryStatus.TOO_OLD
    q = enc.query(3.5)
    assert math.isnan(q.pan) and math.isnan(q.tilt) and math.isnan(q.zoom)


def test_missing_joint_makes_queries_invalid_until_it_arrives():
    enc = EncoderInterpolator()
    enc.add(0.0, {"pan": 0.0, "tilt": 0.0})
    enc.add(0.1, {"pan": 0.1, "tilt": 0.1})
    assert enc.query(0.05).status is QueryStatus.NO_DATA
    enc.add(0.0, {"zoom": 1.0})
    enc.add(0.1, {"zoom": 2.0})
    assert enc.query(0.05).zoom == pytest.approx(1.5)


def test_far_future_stamp_rejected_relative_to_reference_time():
    enc = EncoderInterpolator(EncoderConfig(max_future=10.0))
    feed(enc, [0.0, 0.1])
    assert enc.add(1e6, {"pan": 9.0, "tilt": 9.0, "zoom": 9.0}, reference_time=0.1)[0][1] is Rejection.FUTURE
    assert enc.rejections["future_stamp"] == 3
    feed(enc, [0.2])
    assert enc.query(0.15).valid


def test_memory_is_bounded_and_old_samples_refused_when_full():
    enc = EncoderInterpolator(EncoderConfig(max_samples=50))
    feed(enc, [i * 0.01 for i in range(1000)])
    assert all(enc.sample_count(j) == 50 for j in enc.joints)
    assert enc.query(9.985).valid
    assert enc.add(0.0, {"pan": 0.0, "tilt": 0.0, "zoom": 0.0})[0][1] is Rejection.TOO_OLD


@pytest.mark.parametrize(
    "kwargs",
    [
        {"max_gap": 0.0},
        {"max_gap": float("nan")},
        {"max_samples": 1},
        {"time_offset": 1e9},
        {"joints": ("pan", "pan", "zoom")},
        {"max_hold": -1.0},
    ],
)
def test_absurd_configuration_rejected(kwargs):
    with pytest.raises(ValueError):
        EncoderInterpolator(EncoderConfig(**kwargs))
