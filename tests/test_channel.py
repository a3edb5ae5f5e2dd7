"""The V2V channel: whole-step delay, per-message loss with hold-last, bit counting."""

from __future__ import annotations

import numpy as np
import pytest

from envs.channel import ChannelConfig, V2VChannel, episode_uniforms
from envs.errors import ConfigError


def test_delay_in_whole_steps() -> None:
    ch = V2VChannel.predecessor(2, 1, [0], config=ChannelConfig(delay_s=0.2), initial=-1.0)
    got = [ch.transmit(np.array([[float(t), 10.0 + t, 0.0]]))[0, :, 0].tolist() for t in range(4)]
    assert got == [[-1.0, -1.0], [-1.0, -1.0], [0.0, 10.0], [1.0, 11.0]]


def test_no_delay_is_instant_and_bits_are_counted() -> None:
    ch = V2VChannel.predecessor(3, 2, [0, 1], bits_per_value=32)
    out = ch.transmit(np.arange(2 * 4 * 2, dtype=float).reshape(2, 4, 2))
    np.testing.assert_array_equal(out[0, 0], [0, 1])  # leader -> follower 1
    np.testing.assert_array_equal(out[1, 2], [12, 13])  # follower 2 -> follower 3, episode 2
    # senders 0, 1, 2 (follower 3 sends to no one): 3 senders x 2 floats x 32 bits x 2 episodes
    assert ch.bits_sent == 3 * 2 * 32 * 2
    assert ch.bits_per_vehicle_per_s(3, 1, 0.1) == pytest.approx(3 * 2 * 32 / (3 * 0.1))


def test_loss_holds_last_message_and_rate() -> None:
    ch = V2VChannel.predecessor(4, 1, np.arange(50), config=ChannelConfig(packet_loss=0.3))
    lost = 0
    total = 0
    prev = np.zeros((50, 4))
    for t in range(200):
        out = ch.transmit(np.full((50, 5), float(t + 1)))[:, :, 0]
        fresh = out == t + 1
        held = ~fresh
        np.testing.assert_array_equal(out[held], prev[held])  # a loss keeps the last message
        lost += held.sum()
        total += out.size
        prev = out.copy()
    assert lost / total == pytest.approx(0.3, abs=0.02)


def test_losses_depend_only_on_the_episode_seed() -> None:
    batch = episode_uniforms(np.array([5, 9, 11]), "cacc", 17, 8)
    alone = episode_uniforms(np.array([9]), "cacc", 17, 8)
    np.testing.assert_array_equal(batch[1], alone[0])
    assert not np.array_equal(batch[0], batch[1])
    assert not np.array_equal(episode_uniforms(np.array([9]), "other", 17, 8), alone)
    assert np.all((batch >= 0) & (batch < 1))


@pytest.mark.parametrize(("delay", "loss"), [(-0.1, 0.0), (0.0, -0.1), (0.0, 1.5)])
def test_bad_settings(delay: float, loss: float) -> None:
    with pytest.raises(ConfigError):
        ChannelConfig(delay, loss)
