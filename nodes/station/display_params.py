"""The ``display`` node's parameters: its address and token, its limits, what it shows.

The host is checked when the graph is validated (:func:`_local_host`): a view that cannot
listen fails at ``flowrt validate``, not at every restart of the node."""

from __future__ import annotations

import contextlib
from typing import Annotated

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from flowrt import resolve_path
from flowrt.control import serving


def _local_host(host: str) -> str:
    """An IP address, or a name that resolves to an address of this machine.

    Checked when the graph is validated: a name that does not resolve (``example.invalid``)
    or resolves elsewhere made the view fail to listen at every restart. Resolution is given
    ``RESOLVE_TIMEOUT`` seconds, so a dead DNS server cannot hang ``flowrt validate``.
    """
    import concurrent.futures
    import ipaddress
    import socket

    try:
        ipaddress.ip_address(host)
        return host
    except ValueError:
        pass
    if host in ("", "localhost"):
        return host
    pool = concurrent.futures.ThreadPoolExecutor(1)
    try:
        infos = pool.submit(socket.getaddrinfo, host, None, 0, socket.SOCK_STREAM).result(
            RESOLVE_TIMEOUT
        )
    except concurrent.futures.TimeoutError:
        raise ValueError(
            f"host {host!r} does not resolve (no answer within {RESOLVE_TIMEOUT:g} s): "
            "give an IP address (127.0.0.1, ::1, 0.0.0.0)"
        ) from None
    except (OSError, UnicodeError) as e:
        raise ValueError(
            f"host {host!r} does not resolve ({e}): give an IP address (127.0.0.1, ::1, "
            "0.0.0.0) or a name of this machine"
        ) from None
    finally:
        pool.shutdown(wait=False)
    addresses = sorted({str(info[4][0]) for info in infos})
    for family, _, _, _, sockaddr in infos:
        with contextlib.suppress(OSError), socket.socket(family, socket.SOCK_STREAM) as s:
            s.bind((sockaddr[0], 0))
            return host
    raise ValueError(
        f"host {host!r} resolves to {', '.join(addresses)}, not an address of this machine"
    )


RESOLVE_TIMEOUT = 2.0


class Robot(BaseModel):
    """A robot the base station's view watches and records through its control channel."""

    model_config = ConfigDict(extra="forbid")
    connect: list[str] = Field(
        min_length=1, description="the robot's Zenoh endpoints, e.g. tcp/192.168.1.10:7447"
    )
    control: str = Field(description="the robot graph's zenoh.control key")
    token: str | None = Field(None, description="its control token, when it needs one")

    @field_validator("connect")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        from flowrt.graph.spec import _endpoint

        return [_endpoint(e) for e in v]

    @field_validator("control")
    @classmethod
    def _key(cls, v: str) -> str:
        from flowrt.graph.spec import check_key_expr

        check_key_expr(v, wildcards=False)
        return v


class DisplayParams(BaseModel):
    """What a display is told (a graph's ``params``): where it listens, who may connect,
    how much it encodes, what it shows; the node lives in :mod:`.display`."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    host: Annotated[str, AfterValidator(_local_host)] = Field(
        "127.0.0.1",
        description="address to listen on: an IP address (0.0.0.0: every interface) or a "
        "name of this machine; beyond loopback a token is required",
    )
    port: int = Field(8750, ge=0, le=65535, description="TCP port; 0 picks a free one")
    token: str | None = Field(
        None,
        min_length=8,
        description="required of every client (Bearer header, or ?token= once: a cookie)",
    )
    token_required: bool | None = Field(
        None,
        description="None: required when the graph can drive from the page (a joystick "
        "with source: web), one generated and printed unless token is given; true: always; "
        "false: never, any local process may open the page and drive (an explicit opt-out)",
    )
    allowed_hosts: list[str] = Field(
        default_factory=list,
        description="names besides loopback a browser may use in Host (without a token)",
    )
    max_clients: int = Field(
        32, ge=1, le=1000, description="open connections at once; more are closed at once"
    )
    max_streams: int | None = Field(
        None,
        ge=1,
        le=1000,
        description="MJPEG streams and page WebSockets at once (default: half of "
        "max_clients): the other slots stay for the page, /stats.json and the API",
    )
    max_streams_per_peer: int = Field(
        4, ge=1, le=1000, description="MJPEG streams one client address may hold at once"
    )
    max_fps: float | None = Field(
        None,
        gt=0,
        le=1000,
        description="cap on the frames encoded per second and source; none: the source's rate",
    )
    jpeg_quality: int = Field(80, ge=1, le=100)
    draw_on: dict[str, str] = Field(
        default_factory=dict, description="detection input -> the frame input it is drawn on"
    )
    detection_ttl: float = Field(
        1.0, gt=0, le=3600, description="seconds after which a detection is no longer drawn"
    )
    refresh_ms: int = Field(
        333, ge=50, le=3_600_000, description="how often the page polls the statistics"
    )
    recordings: str | None = Field(
        None,
        description="a folder of recorded sessions to review (besides every recorder's; "
        "relative: beside the graph file); flowrt run --recordings DIR sets it",
    )
    health_hz: float = Field(
        1.0, ge=0.1, le=10, description="machine and stream health samples per second"
    )
    health_keep_s: float = Field(
        900.0, ge=60, le=86400, description="seconds of health history kept for the plots"
    )
    robots: dict[str, Robot] = Field(
        default_factory=dict,
        description="robots (name: their Zenoh control channel) whose state the page shows "
        "and whose recorders it starts and stops",
    )

    @field_validator("recordings", mode="after")
    @classmethod
    def _beside_the_graph(cls, v: str | None, info: ValidationInfo) -> str | None:
        return None if v is None else resolve_path(v, info)

    @model_validator(mode="after")
    def _token_beyond_loopback(self) -> DisplayParams:
        if not self.token and not serving.is_loopback(self.host):
            raise ValueError(
                f"serving the live view on {self.host} needs a token (params.token, or "
                "flowrt run --display-token): any machine that reaches it sees the cameras"
            )
        return self
