"""A sensor kind added from outside the package: a toy barometer declared here, recorded
to a bag and read back bit for bit, and streamed over the robot link beside an
emulator that has never heard of it."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from hardware.bag import BagReader, read_run
from hardware.bag import messages as m
from hardware.bag.codec import MessageError, RobotCodec
from hardware.bag.kinds import (
    Channel,
    SensorKind,
    register_sensor_kind,
    sample_kinds_of_topics,
    sensor_kinds,
    unregister_sensor_kind,
)
from hardware.link import LinkAddress, ZenohDriver
from hardware.link.process import EmulatorProcess
from hardware.link.wire import open_session
from hardware.recording import BagSink, MemorySink, RecordingBackend
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.samples import (
    SAMPLE_KINDS,
    EncoderSample,
    UwbRangeSample,
    ns_to_seconds,
)
from tensegrity_gym.sim.backend import SimBackend

if TYPE_CHECKING:
    from collections.abc import Iterator
    from pathlib import Path

    from hardware.bag.kinds import CodecContext
    from tensegrity_gym.model.protocols import Backend, StepResult

THREE_BAR = load_robot("three_bar")
FLUID_PRESSURE = "sensor_msgs/msg/FluidPressure"
TOPIC = "/barometer/pressure"


@dataclass(frozen=True, slots=True)
class BarometerSample:
    """Static air pressure on the robot's hub."""

    t: float
    pressure: float
    """Pa."""


def _encode(ctx: CodecContext, s: BarometerSample) -> list[bytes]:
    msg = ctx.store.types[FLUID_PRESSURE](
        header=ctx.header(s.t, "hub"), fluid_pressure=float(s.pressure), variance=0.0
    )
    return [ctx.serialize(msg, FLUID_PRESSURE)]


def _decode(ctx: CodecContext, channel: int, rod: int, raw: m.Raw) -> tuple[int, BarometerSample]:
    msg = ctx.deserialize(raw, FLUID_PRESSURE)
    if not math.isfinite(msg.fluid_pressure):
        raise MessageError("the pressure is not finite")
    ns = m.stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)
    return ns, BarometerSample(ctx.seconds(ns), float(msg.fluid_pressure))


# Between the encoders (2) and the cable lengths (3) among samples of one stamp.
BAROMETER = SensorKind(
    "barometer",
    BarometerSample,
    (Channel(TOPIC, FLUID_PRESSURE, "static pressure (Pa)"),),
    _encode,
    _decode,
    order=2.5,
)


@pytest.fixture
def barometer() -> Iterator[SensorKind]:
    register_sensor_kind(BAROMETER)
    try:
        yield BAROMETER
    finally:
        unregister_sensor_kind(BAROMETER.name)
    assert "barometer" not in SAMPLE_KINDS


class WithBarometer:
    """The simulated robot with a barometer read at every encoder sample's time."""

    def __init__(self, inner: Backend) -> None:
        self.inner = inner

    def __getattr__(self, name: str) -> Any:
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def _with_readings(self, result: StepResult) -> StepResult:
        readings = [
            BarometerSample(s.t, 101_325.0 - 11.3 * s.t)
            for s in result.samples
            if isinstance(s, EncoderSample)
        ]
        order = {k.sample: k.order for k in sensor_kinds()}
        samples = sorted(
            [*result.samples, *readings],
            key=lambda s: (s.t, order[type(s)], getattr(s, "rod", 0)),
        )
        return dataclasses.replace(result, samples=samples)

    def reset(self, rng: np.random.Generator, **kwargs: Any) -> StepResult:
        return self._with_readings(self.inner.reset(rng, **kwargs))

    def step(self, targets: Any) -> StepResult:
        return self._with_readings(self.inner.step(targets))


def _same(a: Any, b: Any, where: str) -> None:
    assert type(a) is type(b), where
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), f"{where}.{name}"
        else:
            assert x == y, f"{where}.{name}"


def test_registration_checks_what_it_is_given(barometer: SensorKind) -> None:
    assert SAMPLE_KINDS["barometer"] is BarometerSample
    assert [k.name for k in sensor_kinds()].index("barometer") == 3  # after the encoders
    with pytest.raises(ValueError, match="already registered"):
        register_sensor_kind(barometer)
    clash = dataclasses.replace(barometer, name="barometer2", order=9.0)
    with pytest.raises(ValueError, match="already in the topic table"):
        register_sensor_kind(clash)
    with pytest.raises(ValueError, match="not a known ROS type"):
        register_sensor_kind(
            dataclasses.replace(
                clash, sample=float, channels=(Channel("/baro2", "sensor_msgs/msg/Nope"),)
            )
        )
    with pytest.raises(ValueError, match="two with a pairing"):
        dataclasses.replace(barometer, channels=(*barometer.channels, Channel("/b", m.STRING)))
    with pytest.raises(ValueError, match="built-in"):
        unregister_sensor_kind("uwb")
    codec = RobotCodec(THREE_BAR)
    assert codec.topics.types[TOPIC] == FLUID_PRESSURE
    (topic, raw), *rest = codec.encode_sample(BarometerSample(1.5, 99_000.0))
    assert topic == TOPIC and not rest
    assert BAROMETER.decode(codec, 0, 0, raw) == (1_500_000_000, BarometerSample(1.5, 99_000.0))


def test_a_toy_kind_records_and_reads_back_bit_for_bit(
    barometer: SensorKind, tmp_path: Path
) -> None:
    memory = MemorySink()
    sim = WithBarometer(SimBackend(THREE_BAR))
    backend = RecordingBackend(RecordingBackend(sim, memory), BagSink(tmp_path))
    rng = np.random.default_rng(0)
    backend.reset(rng)
    lo, hi, _ = THREE_BAR.motor_limits
    for _ in range(4):
        backend.step(rng.uniform(lo, hi))
    backend.close()
    live, bag = memory.run, tmp_path / "episode_000"
    back = read_run(bag)
    assert len(back.steps) == len(live.steps) == 4
    periods = zip([back.start, *back.steps], [live.start, *live.steps], strict=True)
    for k, (x, y) in enumerate(periods):
        assert len(x.samples) == len(y.samples), k
        for j, (a, b) in enumerate(zip(x.samples, y.samples, strict=True)):
            _same(a, b, f"period {k} sample {j}")
    samples = [s for step in back.steps for s in step.samples]
    readings = [s for s in samples if isinstance(s, BarometerSample)]
    assert len(readings) == sum(isinstance(s, EncoderSample) for s in samples) > 10
    after = [samples[i - 1] for i, s in enumerate(samples) if isinstance(s, BarometerSample)]
    for before, reading in zip(after, readings, strict=True):  # the table's order, 2.5
        assert isinstance(before, EncoderSample) and before.t == reading.t
    with BagReader(bag) as reader:
        assert reader.topics[TOPIC] == FLUID_PRESSURE
        assert "barometer" in sample_kinds_of_topics(reader.topics, reader.description)
        list(reader.periods())
        assert not reader.skipped
    unregister_sensor_kind("barometer")  # a reader that does not know the kind skips it
    with BagReader(bag) as reader:
        list(reader.periods())
        assert reader.skipped["unknown_topic"] == len(readings) + sum(
            isinstance(s, BarometerSample) for s in live.start.samples
        )


def test_a_toy_kind_streams_over_the_link_in_stamp_order(barometer: SensorKind) -> None:
    with EmulatorProcess("three_bar") as emulator:
        address = LinkAddress.parse(emulator.address)
        robot_side = open_session(address, listen=False, timeout=5.0)
        driver = ZenohDriver(THREE_BAR, address)
        try:
            publisher = robot_side.declare_publisher(address.key(TOPIC))
            driver.reset(np.random.default_rng(0))
            start = time.time_ns() - driver.clock_origin_ns  # ns of sample time, now
            sent = [
                BarometerSample(ns_to_seconds(start + k * 5_000_000), 100_000.0 + k)
                for k in range(20)
            ]
            for k in np.random.default_rng(1).permutation(len(sent)):
                publisher.put(driver.codec.encode_sample(sent[k])[0][1])  # overtaking
            hold = THREE_BAR.rest_lengths[THREE_BAR.actuated]
            got: list[BarometerSample] = []
            for _ in range(20):
                result = driver.step(hold)
                times = [s.t for s in result.samples]
                assert times == sorted(times)
                assert any(isinstance(s, UwbRangeSample | EncoderSample) for s in result.samples)
                got += [s for s in result.samples if isinstance(s, BarometerSample)]
                if len(got) >= len(sent):
                    break
            counts = driver.link_counts()
        finally:
            driver.close()
            robot_side.close()
    assert [s.pressure for s in got] == [s.pressure for s in sent]  # sorted by stamp
    assert [s.t for s in got] == [s.t for s in sent]
    assert counts["reordered"] > 0 and counts.get("undecodable", 0) == 0
