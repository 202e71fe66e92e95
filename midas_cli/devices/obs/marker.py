"""The optional sync marker: a scene item OBS shows and hides at known host times.

The item (any source in the scene, e.g. a white colour source over a corner) is hidden when the
recording starts, shown ``at`` s after STARTED for ``on`` s, and again every ``every`` s (0: once).
Each toggle is a row (seq, t_host_ns before the request, t_ack_ns after OBS answered, enabled):
finding the first frame that shows the item (midas_cli.analysis.video_marker) gives the true offset
between the video's frame times and the host clock.
"""

from __future__ import annotations

from dataclasses import dataclass

from midas_cli.clock import HostClock
from midas_cli.devices.obs.connection import ObsConnection
from midas_cli.errors import ConfigError
from midas_cli.session.schema import SEQ, Column, StreamSpec


@dataclass(frozen=True)
class MarkerPlan:
    """``source`` in ``scene`` ("" = the current program scene); times in s after STARTED."""

    source: str
    scene: str = ""
    at: float = 1.0
    on: float = 0.5
    every: float = 0.0

    def __post_init__(self) -> None:
        if self.at < 0 or self.on <= 0:
            raise ConfigError(f"sync marker: marker_at must be >= 0 and marker_on > 0 s, got {self.at}, {self.on}")
        if self.every and self.every <= self.on:
            raise ConfigError(f"sync marker: marker_every ({self.every} s) must exceed marker_on ({self.on} s)")

    def spec(self, device: str) -> StreamSpec:
        columns = (SEQ, Column("t_host_ns", "int", "ns", clock="host", description="host time before the request"),
                   Column("t_ack_ns", "int", "ns", clock="host", description="host time OBS acknowledged it"),
                   Column("enabled", "int", "bool", description="1 shown, 0 hidden"))
        return StreamSpec(f"{device}_marker", device, columns, None,
                          f"sync marker toggles of scene item {self.source!r} (events: no nominal rate)")


class SyncMarker:
    """Toggles the marker item on schedule; ``due`` rows are produced by ``poll``. Creating it only reads
    the item's visibility (saved before anything changes); ``hide`` hides it for the recording."""

    def __init__(self, plan: MarkerPlan, connection: ObsConnection, clock: HostClock) -> None:
        self.plan = plan
        self.connection = connection
        self.clock = clock
        self.scene = plan.scene or connection.request("GetCurrentProgramScene")["currentProgramSceneName"]
        found = connection.request("GetSceneItemId", {"sceneName": self.scene, "sourceName": plan.source})
        self.item_id = int(found["sceneItemId"])
        self.was_enabled = bool(self._request_enabled())
        self.toggles = 0
        self.started_ns: int | None = None

    def saved_state(self) -> dict:
        """The operator's visibility of the item, for the saved copy of OBS's settings."""
        return {"scene": self.scene, "item_id": self.item_id, "enabled": self.was_enabled}

    def hide(self) -> None:
        self._set(False)

    def _request_enabled(self) -> bool:
        return self.connection.request("GetSceneItemEnabled", {"sceneName": self.scene,
                                                               "sceneItemId": self.item_id})["sceneItemEnabled"]

    def _set(self, enabled: bool) -> tuple[int, int]:
        before = self.clock.now_ns()
        self.connection.request("SetSceneItemEnabled", {"sceneName": self.scene, "sceneItemId": self.item_id,
                                                        "sceneItemEnabled": enabled})
        return before, self.clock.now_ns()

    def next_due_ns(self) -> int | None:
        """Host time of the next toggle (None: none left or not started)."""
        if self.started_ns is None or (not self.plan.every and self.toggles >= 2):
            return None
        showing, period = divmod(self.toggles, 2)
        offset = self.plan.at + showing * self.plan.every + (self.plan.on if period else 0.0)
        return self.started_ns + round(offset * 1e9)

    def poll(self) -> list[tuple[int, int, int, int]]:
        """Toggle if due; the rows (seq, t_host_ns, t_ack_ns, enabled) of the toggles made."""
        due = self.next_due_ns()
        if due is None or self.clock.now_ns() < due:
            return []
        enabled = self.toggles % 2 == 0
        before, ack = self._set(enabled)
        self.toggles += 1
        return [(self.toggles - 1, before, ack, int(enabled))]

    def restore(self) -> None:
        """Leave the item as the operator had it."""
        self._set(self.was_enabled)
