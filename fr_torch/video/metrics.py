"""Live metrics of a running ``fr track`` (one source or a fleet), served for Prometheus.

``fr track ... --metrics [HOST:]PORT`` serves Prometheus's text format at
``http://HOST:PORT/metrics`` (``prometheus-client``'s server, a thread of the process; HOST
defaults to 127.0.0.1: only this machine can scrape it unless another address is given).  Every
value is read from the cameras when the page is scraped (:class:`TrackCollector`), so a run
without scrapes does no work for them, and the fused values are those of each camera's
``calibration.json`` (:attr:`fr_torch.video.records.TrackOutput.calibration`).

Per camera (label ``camera``: the camera's name in a fleet, the source's short name
(:attr:`fr_torch.video.sources.Source.label`) for one source; never a URL), prefix ``fr_track_``:

=======================================  ========  =================================================
metric                                   type      value
=======================================  ========  =================================================
``focal_px``, ``tilt_deg``, ``roll_deg``  gauge     the fused calibration (absent before the first
                                                   accepted frame)
``focal_sigma_pct``, ``tilt_sigma_deg``,  gauge     its standard deviations (a 90 % bound is 1.645
``roll_sigma_deg``                                 times them); ``horizon_bound_pct``: the fused
                                                   horizon's 90 % bound, % of the height (absent
                                                   when unbounded: ``horizon_unbounded`` 1)
``calibrated``                            gauge     1 when a fused calibration exists
``reliable``                              gauge     1 when the latest searched frame was reliable
``up``                                    gauge     1 while the camera runs and its source delivers;
                                                   0 during an outage and once it has ended
``last_good_age_seconds``                 gauge     seconds since the latest accepted frame's record
                                                   (absent before one)
``frames_read_total``                     counter   frames read from the source (every segment)
``frames_searched_total``                 counter   frames searched and recorded (every segment)
``frames_accepted_total``                 counter   of them fused into the calibration
``frames_dropped_total``                  counter   live frames dropped in real time (every segment)
``reconnects_total``                      counter   reconnections of the source in this run
=======================================  ========  =================================================
"""
from __future__ import annotations

import ipaddress
import time
from dataclasses import dataclass
from typing import Callable, Iterator, Sequence

from prometheus_client import CollectorRegistry, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from fr_torch.errors import FRInputError
from fr_torch.runtime.schema import is_finite_number

#: The metrics' prefix.
PREFIX = "fr_track_"
#: The address ``--metrics PORT`` binds to: this machine only.
DEFAULT_HOST = "127.0.0.1"


@dataclass(frozen=True)
class MetricsAddress:
    """Where ``--metrics`` serves: ``host`` (an IP address or name; default
    :data:`DEFAULT_HOST`) and ``port`` (0: any free port)."""

    host: str
    port: int

    @classmethod
    def parse(cls, text: str) -> MetricsAddress:
        """``PORT``, ``HOST:PORT`` or ``[IPV6]:PORT``; FRInputError (one line) otherwise."""
        host, colon, port = str(text).rpartition(":")
        host = host.strip("[]") if colon else DEFAULT_HOST
        try:
            number = int(port)
        except ValueError:
            number = -1
        if not 0 <= number <= 65535 or (colon and not host):
            raise FRInputError(f"--metrics: expected PORT or HOST:PORT (e.g. 9464 or 0.0.0.0:9464), got {text!r}")
        return cls(host, number)

    @property
    def url_host(self) -> str:
        try:
            return f"[{self.host}]" if ipaddress.ip_address(self.host).version == 6 else self.host
        except ValueError:
            return self.host


#: (metric name without prefix, help, key of calibration.json's ``calibration`` or None, key in its ``sigma``)
FUSED = (("focal_px", "fused focal length, pixels", "focal_px", None),
         ("tilt_deg", "fused tilt (the paper's, horizon-based), degrees", "tilt_deg", None),
         ("roll_deg", "fused roll, degrees", "roll_deg", None),
         ("focal_sigma_pct", "standard deviation of the fused focal length, % (90 % bound: 1.645 x)", None,
          "focal_pct"),
         ("tilt_sigma_deg", "standard deviation of the fused tilt, degrees (90 % bound: 1.645 x)", None, "tilt_deg"),
         ("roll_sigma_deg", "standard deviation of the fused roll, degrees (90 % bound: 1.645 x)", None, "roll_deg"))


class TrackCollector:
    """A Prometheus collector of the cameras ``cameras()`` returns, read at each scrape: pairs of
    (label, :class:`fr_torch.video.track.Tracking`)."""

    def __init__(self, cameras: Callable[[], Sequence[tuple[str, object]]]):
        self.cameras = cameras

    def collect(self) -> Iterator:
        now = time.time()
        families = {}

        def family(kind, name: str, text: str):
            if name not in families:
                families[name] = kind(PREFIX + name, text, labels=["camera"])
            return families[name]

        for label, tracking in self.cameras():
            output, stream = tracking.output, tracking.stream
            calibration = output.calibration or {}
            for name, text, key, sigma_key in FUSED:
                value = calibration.get(key) if key else (calibration.get("sigma") or {}).get(sigma_key)
                if is_finite_number(value):
                    family(GaugeMetricFamily, name, text).add_metric([label], float(value))
            horizon = calibration.get("horizon") or {}
            if is_finite_number(horizon.get("bound_pct")):
                family(GaugeMetricFamily, "horizon_bound_pct", "90 % bound of the fused horizon at the image "
                       "borders, % of the image height").add_metric([label], float(horizon["bound_pct"]))
            if horizon:
                family(GaugeMetricFamily, "horizon_unbounded", "1 when the fused horizon has no bound"
                       ).add_metric([label], float(bool(horizon.get("unbounded"))))
            family(GaugeMetricFamily, "calibrated", "1 when the camera has a fused calibration"
                   ).add_metric([label], float(bool(calibration)))
            family(GaugeMetricFamily, "reliable", "1 when the latest searched frame was reliable"
                   ).add_metric([label], float(bool(output.last_reliable)))
            family(GaugeMetricFamily, "up", "1 while the camera runs and its source delivers frames"
                   ).add_metric([label], float(not tracking.ended and not stream.outage))
            if output.last_accepted_at is not None:
                family(GaugeMetricFamily, "last_good_age_seconds", "seconds since the latest accepted frame"
                       ).add_metric([label], max(0.0, now - output.last_accepted_at))
            totals = output.totals
            for name, text, value in (
                    ("frames_read", "frames read from the source, every segment", totals.arrived + stream.arrived),
                    ("frames_searched", "frames searched and recorded, every segment", totals.processed),
                    ("frames_accepted", "frames fused into the calibration, every segment", totals.accepted),
                    ("frames_dropped", "live frames dropped in real time, every segment",
                     totals.dropped + stream.dropped),
                    ("reconnects", "reconnections of the source in this run", stream.reconnects)):
                family(CounterMetricFamily, name, text).add_metric([label], float(value))
        yield from families.values()


class MetricsServer:
    """The metrics page of ``cameras`` (:class:`TrackCollector`) served at ``address`` by a thread
    of this process until :meth:`close`; ``url`` is where (the port chosen when 0 was asked)."""

    def __init__(self, address: MetricsAddress, cameras: Callable[[], Sequence[tuple[str, object]]]):
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(TrackCollector(cameras))
        try:
            self._server, self._thread = start_http_server(address.port, address.host, self.registry)
        except OSError as exc:
            raise FRInputError(f"--metrics {address.host}:{address.port}: cannot serve there "
                               f"({exc.strerror or exc})") from None
        port = self._server.server_address[1]
        self.url = f"http://{address.url_host}:{port}/metrics"

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(5.0)
