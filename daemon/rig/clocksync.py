"""Phone sensor clock -> host loop clock, and the beam angle at which an image was exposed.

A phone stamps each image with SENSOR_TIMESTAMP (ns, start of exposure) on its own clock.
Clock-sync pings give samples (host_send_s, device_ns, host_recv_s): the device read its
clock somewhere between send and receive. As in Klipper's clocksync, only the samples with
the smallest round trip carry a tight bound, so the fit keeps those and regresses host
time (the round trip's midpoint) on device time: offset plus drift. The uncertainty is half
the best round trip (where in the round trip the device read its clock is unknown) plus the
fit's residual spread.

The exposure angle of an image is the encoder trace (host time, beam angle) interpolated at
the host time of the middle of the exposure.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from daemon.errors import DaemonError

if TYPE_CHECKING:
    from drivers.phone.camera import ClockSample


class ClockSyncError(DaemonError):
    """Base of the clock mapping errors."""


class NotSynchronised(ClockSyncError):
    """No usable clock-sync sample yet for this phone."""


class BadSample(ClockSyncError):
    """A clock-sync sample is impossible (receive before send, non-finite)."""


class OutsideTrace(ClockSyncError):
    """A time lies outside the recorded encoder trace, or in a gap of it."""

    def __init__(self, time_s: float, start_s: float, end_s: float, why: str = "outside") -> None:
        self.time_s = time_s
        self.start_s = start_s
        self.end_s = end_s
        super().__init__(
            f"host time {time_s:.6f} s is {why} the encoder trace [{start_s:.6f}, {end_s:.6f}] s"
        )


@dataclass(frozen=True)
class ClockFit:
    """host_s = ref_host_s + (device_ns - ref_device_ns) * 1e-9 * rate.

    rate is host seconds per device second (1 + drift); uncertainty_s bounds the mapping error.
    """

    ref_device_ns: int
    ref_host_s: float
    rate: float
    uncertainty_s: float
    samples_used: int
    best_rtt_s: float

    @property
    def drift_ppm(self) -> float:
        return (self.rate - 1.0) * 1e6

    def to_host(self, device_ns: int | np.ndarray) -> float | np.ndarray:
        """Host loop time (s) of device clock reading(s) (ns)."""
        dt: float | np.ndarray
        if isinstance(device_ns, np.ndarray):
            dt = (device_ns.astype(np.int64) - self.ref_device_ns).astype(float) * 1e-9
        else:
            dt = (int(device_ns) - self.ref_device_ns) * 1e-9
        return self.ref_host_s + dt * self.rate


class ClockSync:
    """Keeps the latest WINDOW samples of one phone and fits its clock from the best of them.

    KEEP_FRACTION of the samples with the smallest round trip (at least MIN_KEEP) enter the
    regression; with a single sample the rate is taken as 1.
    """

    WINDOW = 64
    KEEP_FRACTION = 0.25
    MIN_KEEP = 4

    def __init__(self, name: str = "phone") -> None:
        self.name = name
        self._samples: deque[tuple[float, int, float]] = deque(maxlen=self.WINDOW)
        self._fit: ClockFit | None = None

    def add(self, sample: ClockSample) -> None:
        send, recv = float(sample.host_send_s), float(sample.host_recv_s)
        if not (math.isfinite(send) and math.isfinite(recv)) or recv < send:
            raise BadSample(
                f"{self.name}: clock sample sent at {send!r} s, received at {recv!r} s"
            )
        self._samples.append((send, int(sample.device_ns), recv))
        self._fit = None

    def extend(self, samples: Iterable[ClockSample]) -> None:
        for s in samples:
            self.add(s)

    @property
    def fit(self) -> ClockFit:
        if self._fit is None:
            self._fit = self._compute()
        return self._fit

    def to_host(self, device_ns: int) -> float:
        return float(self.fit.to_host(device_ns))

    def _compute(self) -> ClockFit:
        if not self._samples:
            raise NotSynchronised(f"{self.name}: no clock-sync sample yet")
        send = np.array([s[0] for s in self._samples])
        dev = np.array([s[1] for s in self._samples], dtype=np.int64)
        recv = np.array([s[2] for s in self._samples])
        rtt = recv - send
        keep = max(min(self.MIN_KEEP, len(rtt)), int(len(rtt) * self.KEEP_FRACTION))
        best = np.argsort(rtt, kind="stable")[:keep]
        mid = 0.5 * (send[best] + recv[best])
        ref_dev = int(dev[best[0]])
        x = (dev[best] - ref_dev).astype(float) * 1e-9
        best_rtt = float(rtt[best[0]])
        if len(best) >= 2 and np.ptp(x) > 0:
            rate, intercept = np.polyfit(x, mid, 1)
            residual = mid - (intercept + rate * x)
            spread = float(np.sqrt(np.mean(residual**2)))
        else:
            rate = 1.0
            intercept = float(np.mean(mid - x))
            spread = 0.0
        return ClockFit(
            ref_device_ns=ref_dev, ref_host_s=float(intercept), rate=float(rate),
            uncertainty_s=0.5 * best_rtt + 2.0 * spread, samples_used=len(best),
            best_rtt_s=best_rtt,
        )


@dataclass(frozen=True)
class ExposureAngle:
    """Beam angle (deg) at the middle of an exposure, its host time (s) and uncertainty (deg)."""

    angle_deg: float
    host_time_s: float
    uncertainty_deg: float


class EncoderTrace:
    """The beam's encoder trace: (N,) host loop times s (non-decreasing) and angles deg."""

    MAX_GAP_S = 0.1

    def __init__(self, time_s: np.ndarray, angle_deg: np.ndarray) -> None:
        t = np.asarray(time_s, dtype=float)
        a = np.asarray(angle_deg, dtype=float)
        if t.ndim != 1 or t.shape != a.shape or len(t) < 2:
            raise ClockSyncError(
                f"encoder trace needs two equal (N,) arrays with N >= 2, got {t.shape} and {a.shape}"
            )
        if np.any(np.diff(t) < 0):
            i = int(np.argmax(np.diff(t) < 0))
            raise ClockSyncError(f"encoder trace times go backwards at sample {i}: "
                                 f"{t[i]:.6f} then {t[i + 1]:.6f} s")
        # Samples delivered in one burst share a loop time: keep the last of each.
        last = np.r_[np.diff(t) > 0, True]
        if np.count_nonzero(last) < 2:
            raise ClockSyncError(f"encoder trace spans no time: all samples at {t[0]:.6f} s")
        self.time_s = t[last]
        self.angle_deg = a[last]

    def angle_at(self, time_s: float) -> float:
        """Interpolated beam angle (deg); OutsideTrace outside the trace or inside a gap."""
        t = self.time_s
        if not t[0] <= time_s <= t[-1]:
            raise OutsideTrace(time_s, float(t[0]), float(t[-1]))
        i = int(np.clip(np.searchsorted(t, time_s, side="right") - 1, 0, len(t) - 2))
        if t[i + 1] - t[i] > self.MAX_GAP_S:
            raise OutsideTrace(time_s, float(t[0]), float(t[-1]),
                               f"in a {t[i + 1] - t[i]:.3f} s gap of")
        return float(np.interp(time_s, t, self.angle_deg))

    def speed_at(self, time_s: float) -> float:
        """Beam speed (deg/s) over the trace interval holding time_s."""
        t = self.time_s
        i = int(np.clip(np.searchsorted(t, time_s, side="right") - 1, 0, len(t) - 2))
        return float((self.angle_deg[i + 1] - self.angle_deg[i]) / (t[i + 1] - t[i]))


def exposure_angle(sensor_timestamp_ns: int, clock: ClockFit | ClockSync, trace: EncoderTrace, *,
                   exposure_s: float = 0.0) -> ExposureAngle:
    """Beam angle at the middle of the exposure that started at ``sensor_timestamp_ns``.

    Raises:
        NotSynchronised: the phone's clock has no sample yet.
        OutsideTrace: the exposure lies outside the encoder trace or in a gap of it.
    """
    fit = clock.fit if isinstance(clock, ClockSync) else clock
    host = float(fit.to_host(sensor_timestamp_ns)) + 0.5 * exposure_s
    angle = trace.angle_at(host)
    return ExposureAngle(angle, host, abs(trace.speed_at(host)) * fit.uncertainty_s)
