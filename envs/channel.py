"""The V2V channel: whole-step delay, per-message packet loss with hold-last, bit counting.

Every controller that communicates sends through a :class:`V2VChannel`, so delay and loss act on
every family alike and every bit is counted. Losses are drawn from the episode's own random
stream: a counter-based hash of (episode seed, channel name, step, link), so a batch of episodes
gives exactly the numbers of the same episodes run one by one, on every executor.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from envs.streams import episode_uniforms
from infra.errors import ConfigError


@dataclass(frozen=True)
class ChannelConfig:
    """V2V settings of a run.

    Attributes
    ----------
    delay_s : float
        Transport delay, rounded to whole steps (0 = instant, as published).
    packet_loss : float
        Probability that one message is lost, in [0, 1]; a receiver keeps its last message.
    dt_s : float
        Step length used to turn the delay into steps.
    """

    delay_s: float = 0.0
    packet_loss: float = 0.0
    dt_s: float = 0.1

    def __post_init__(self) -> None:
        from infra.limits import check_delay, check_packet_loss

        check_delay(self.delay_s, "the V2V delay")  # one rule with --comm-delay and --delay
        check_packet_loss(self.packet_loss)

    @property
    def delay_steps(self) -> int:
        """Delay in whole steps (``round(delay_s / dt_s)``)."""
        return int(round(self.delay_s / self.dt_s + 1e-9))


class V2VChannel:
    """Messages along fixed directed links between vehicles (0 = leader, 1..N followers).

    Each step every sender broadcasts one message (a vector of ``width`` numbers) and every link
    delivers it to its receiver after ``delay_steps`` steps unless it is lost; a receiver that got
    nothing new keeps the last message it received (or ``initial`` before the first one).

    Parameters
    ----------
    links : sequence of (src, dst)
        Directed links by vehicle index.
    width : int
        Numbers per message.
    seeds : (B,) ints
        Episode seeds (losses come from each episode's own stream).
    config : ChannelConfig
        Delay and loss.
    bits_per_value : int
        Bits per transmitted number (32 for float32); counted once per sender and step
        (broadcast: one transmission reaches all of the sender's receivers).
    name : str
        Stream name; two channels of one controller need distinct names.
    initial : float or (B, L, width) array
        What a receiver holds before its first message.
    silent : sequence of int
        Vehicles that send nothing (human drivers in a mixed string): their links never deliver
        (the receiver keeps ``initial``) and they are not counted as senders.
    """

    def __init__(
        self,
        links: Sequence[tuple[int, int]],
        width: int,
        seeds: Sequence[int] | np.ndarray,
        config: ChannelConfig = ChannelConfig(),
        bits_per_value: int = 32,
        name: str = "v2v",
        initial: float | np.ndarray = 0.0,
        silent: Sequence[int] = (),
    ) -> None:
        if width < 1:
            raise ConfigError("a message carries at least one number")
        self.links = np.asarray(links, dtype=np.int64).reshape(-1, 2)
        self.src = self.links[:, 0]
        quiet = np.isin(self.src, np.asarray(list(silent), dtype=np.int64))
        #: (L,) False on the links of a silent sender (None: every link is live)
        self._live: np.ndarray | None = ~quiet if quiet.any() else None
        self.senders = np.unique(self.src[~quiet])
        self.width = int(width)
        self.seeds = np.asarray(seeds, dtype=np.int64).reshape(-1)
        self.config = config
        self.bits_per_value = int(bits_per_value)
        self.name = name
        b, n_links = len(self.seeds), len(self.links)
        self.delay = config.delay_steps
        self._held = np.broadcast_to(
            np.asarray(initial, dtype=np.float64), (b, n_links, self.width)
        ).copy()
        # ring of the last `delay` transmissions, per link (None until sent)
        self._queue: list[np.ndarray | None] = [None] * self.delay
        self._step = 0
        self.bits_sent = 0  # over all episodes of the batch
        self.messages_sent = 0

    def transmit(self, payload: np.ndarray) -> np.ndarray:
        """Send this step's messages and return what the receivers hold now.

        Parameters
        ----------
        payload : (B, V, width) or (B, V)
            Message of every vehicle index ``0..V-1`` (rows of non-senders are ignored).

        Returns
        -------
        (B, L, width)
            Message held by the receiver of each link, in link order.
        """
        payload = np.asarray(payload, dtype=np.float64)
        if payload.ndim == 2:
            payload = payload[:, :, None]
        b = len(self.seeds)
        if payload.shape[0] != b or payload.shape[2] != self.width:
            raise ValueError(
                f"payload shape {payload.shape} does not fit (B={b}, V, width={self.width})"
            )
        sent = payload[:, self.src, :]
        self.bits_sent += b * len(self.senders) * self.width * self.bits_per_value
        self.messages_sent += b * len(self.senders)
        if self.delay:
            self._queue.append(sent)
            arriving = self._queue.pop(0)
        else:
            arriving = sent
        if arriving is not None:
            if self.config.packet_loss > 0:
                u = episode_uniforms(self.seeds, self.name, self._step, len(self.links))
                ok = u >= self.config.packet_loss
                if self._live is not None:
                    ok &= self._live[None, :]
                self._held = np.where(ok[:, :, None], arriving, self._held)
            elif self._live is not None:
                self._held = np.where(self._live[None, :, None], arriving, self._held)
            else:
                self._held = arriving.copy()
        self._step += 1
        return self._held

    @property
    def transmissions(self) -> int:
        """Steps sent so far (calls of :meth:`transmit`)."""
        return self._step

    def bits_per_vehicle_per_s(self, n_vehicles: int, n_steps: int, dt_s: float) -> float:
        """Mean V2V load: bits sent per vehicle (followers) per second, per episode."""
        if n_steps == 0:
            return 0.0
        b = len(self.seeds)
        return self.bits_sent / (b * n_vehicles * n_steps * dt_s)
