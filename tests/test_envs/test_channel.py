"""The V2V channel: whole-step delay, per-message loss with hold-last, bit counting."""

from __future__ import annotations

import numpy as np
import pytest

from envs.channel import ChannelConfig, V2VChannel
from envs.streams import episode_uniforms
from infra.errors import ConfigError


def _chain(n_vehicles: int, width: int, seeds, **kwargs) -> V2VChannel:
    """A channel on the links ``i-1 -> i`` for followers ``i = 1..N``."""
    return V2VChannel([(i - 1, i) for i in range(1, n_vehicles + 1)], width, seeds, **kwargs)


def test_delay_in_whole_steps() -> None:
    ch = _chain(2, 1, [0], config=ChannelConfig(delay_s=0.2), initial=-1.0)
    got = [ch.transmit(np.array([[float(t), 10.0 + t, 0.0]]))[0, :, 0].tolist() for t in range(4)]
    assert got == [[-1.0, -1.0], [-1.0, -1.0], [0.0, 10.0], [1.0, 11.0]]


def test_no_delay_is_instant_and_bits_are_counted() -> None:
    ch = _chain(3, 2, [0, 1], bits_per_value=32)
    out = ch.transmit(np.arange(2 * 4 * 2, dtype=float).reshape(2, 4, 2))
    np.testing.assert_array_equal(out[0, 0], [0, 1])  # leader -> follower 1
    np.testing.assert_array_equal(out[1, 2], [12, 13])  # follower 2 -> follower 3, episode 2
    # senders 0, 1, 2 (follower 3 sends to no one): 3 senders x 2 floats x 32 bits x 2 episodes
    assert ch.bits_sent == 3 * 2 * 32 * 2
    assert ch.bits_per_vehicle_per_s(3, 1, 0.1) == pytest.approx(3 * 2 * 32 / (3 * 0.1))


def test_loss_holds_last_message_and_rate() -> None:
    ch = _chain(4, 1, np.arange(50), config=ChannelConfig(packet_loss=0.3))
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


def test_a_block_of_steps_equals_one_call_per_step() -> None:
    seeds = np.array([3, 2000, 41])
    block = episode_uniforms(seeds, "ACTION", 57, 5, steps=9)
    assert block.shape == (9, 3, 5)
    for k in range(9):
        np.testing.assert_array_equal(block[k], episode_uniforms(seeds, "ACTION", 57 + k, 5))


@pytest.mark.parametrize(("delay", "loss", "message"), [
    (-0.1, 0.0, r"delay must lie in \[0, 60\] s \(an episode lasts 60 s\), got -0.1"),
    (float("nan"), 0.0, r"delay must lie in \[0, 60\] s \(an episode lasts 60 s\), got nan"),
    (1e9, 0.0, r"delay must lie in \[0, 60\] s \(an episode lasts 60 s\), got 1000000000.0"),
    (float("inf"), 0.0, r"delay must lie in \[0, 60\] s \(an episode lasts 60 s\), got inf"),
    (0.0, -0.1, r"loss must lie in \[0, 1\], got -0.1"),
    (0.0, 1.5, r"loss must lie in \[0, 1\], got 1.5"),
])
def test_bad_settings(delay: float, loss: float, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        ChannelConfig(delay, loss)
    with pytest.raises(ConfigError, match="a message carries at least one number"):
        V2VChannel([(0, 1)], 0, [0])


def test_the_loss_stream_is_pinned() -> None:
    """The draws that decide packet loss: a change of stream changes every degraded result, so
    it must show here (values of this implementation, recorded when it was written)."""
    got = episode_uniforms(np.array([2000, 7]), "v2v", 0, 3)
    np.testing.assert_array_equal(got, [[0.22369473213981983, 0.5386997728477074, 0.3376136043193273],
                                        [0.8322180698026723, 0.5282459126009513, 0.43756019354839015]])
    np.testing.assert_array_equal(episode_uniforms(np.array([2000]), "v2v", 5, 2),
                                  [[0.14931142758464422, 0.006595449367496786]])


@pytest.mark.parametrize(("delay_s", "steps"), [(0.0, 0), (0.04, 0), (0.06, 1), (0.1, 1),
                                                (0.149, 1), (0.151, 2), (0.2, 2), (0.3, 3)])
def test_delay_rounds_to_the_nearest_whole_step(delay_s: float, steps: int) -> None:
    assert ChannelConfig(delay_s=delay_s).delay_steps == steps


def _expected(seed: int, n_steps: int, delay: int, loss: float, n_links: int) -> np.ndarray:
    """What each receiver holds when every sender sends its step index + 1 at every step.

    Written from the rule, not the code: the message sent at step t arrives at step t + delay;
    it is lost when the draw of the arrival step and link is below ``loss``; a receiver keeps its
    last message (0 before the first).
    """
    held = np.zeros(n_links)
    out = []
    for t in range(n_steps):
        sent_at = t - delay
        if sent_at >= 0:
            u = episode_uniforms(np.array([seed]), "v2v", t, n_links)[0]
            arrived = u >= loss
            held = np.where(arrived, float(sent_at + 1), held)
        out.append(held.copy())
    return np.array(out)


@pytest.mark.parametrize("delay_s", [0.0, 0.1, 0.2])
@pytest.mark.parametrize("loss", [0.0, 0.3, 0.7, 1.0])
def test_delay_and_loss_together_follow_the_rule(delay_s: float, loss: float) -> None:
    seeds = [2000, 2010]
    cfg = ChannelConfig(delay_s=delay_s, packet_loss=loss)
    ch = _chain(3, 1, seeds, config=cfg)
    got = np.array([ch.transmit(np.full((2, 4), float(t + 1)))[:, :, 0] for t in range(40)])
    for b, seed in enumerate(seeds):
        want = _expected(seed, 40, cfg.delay_steps, loss, 3)
        np.testing.assert_array_equal(got[:, b, :], want)
    if loss == 1.0:
        assert np.all(got == 0.0)  # nothing ever arrives: the initial value is held
    if loss == 0.0:
        assert np.all(got[-1] == 40 - cfg.delay_steps)


def test_a_broadcast_is_lost_per_link_and_counted_once_per_sender() -> None:
    """One sender, two receivers (front and rear neighbours): each link draws its own loss, and
    the transmission is counted once."""
    links = [(1, 0), (1, 2)]
    ch = V2VChannel(links, 1, [2000], config=ChannelConfig(packet_loss=0.5), name="v2v")
    got = np.array([ch.transmit(np.full((1, 3), float(t + 1)))[0, :, 0] for t in range(60)])
    want = _expected(2000, 60, 0, 0.5, 2)
    np.testing.assert_array_equal(got, want)
    assert np.any(got[:, 0] != got[:, 1])  # the two receivers do not share their losses
    assert ch.bits_sent == 60 * 1 * 32 and ch.messages_sent == 60


def test_payload_shape_counts_and_rates() -> None:
    """A payload of the wrong width is refused (the batch size right); messages count once per
    sender and episode; the per-vehicle rate divides by episodes, vehicles and time."""
    ch = _chain(3, 2, [0, 1])  # senders: leader, followers 1 and 2
    with pytest.raises(ValueError, match=r"does not fit \(B=2, V, width=2\)"):
        ch.transmit(np.zeros((2, 4, 3)))
    for _ in range(10):
        ch.transmit(np.zeros((2, 4, 2)))
    assert ch.messages_sent == 10 * 2 * 3
    assert ch.bits_sent == 10 * 2 * 3 * 2 * 32
    assert ch.bits_per_vehicle_per_s(3, 10, 0.1) == pytest.approx(10 * 2 * 3 * 2 * 32 / (2 * 3 * 10 * 0.1))
    assert ch.bits_per_vehicle_per_s(3, 0, 0.1) == 0.0


def test_declared_messages_get_channels_with_the_runs_settings() -> None:
    """The closed loop opens one channel per declared message, with the run's delay and loss (on
    the run's dt) and the declared links; a controller takes it by name and nothing else."""
    from controllers.base import EpisodeContext, Message
    from envs.params import PlatoonParams
    from envs.scenarios import make_scenario
    from infra.errors import ControllerContractError

    ctx = EpisodeContext(make_scenario("catchup-v1"), 3, np.array([5, 6]),
                         PlatoonParams(dt_s=0.2), ChannelConfig(delay_s=0.4, packet_loss=0.1))
    ctx.open_channels([Message("a", 2, "predecessor", initial=np.nan),
                       Message("b", 1, "neighbours", bits_per_value=8),
                       Message("c", 3, "to_leader"), Message("d", 1, ((2, 1),))])
    a, b, c, d = (ctx.channel(k) for k in "abcd")
    assert a.delay == 2 and a.config.packet_loss == 0.1 and a.width == 2
    assert a.links.tolist() == [[0, 1], [1, 2], [2, 3]] and np.isnan(a._held).all()
    assert b.links.tolist() == [[1, 2], [2, 3], [2, 1], [3, 2]] and b.bits_per_value == 8
    assert c.links.tolist() == [[1, 0], [2, 0], [3, 0]] and d.links.tolist() == [[2, 1]]
    assert a.seeds.tolist() == [5, 6]
    with pytest.raises(ControllerContractError, match="no channel 'e' is open: declare it"):
        ctx.channel("e")
    with pytest.raises(ControllerContractError, match="two messages are named 'a'"):
        ctx.open_channels([Message("a", 1)])
    with pytest.raises(ControllerContractError, match="message 'r': unknown link pattern 'ring'"):
        Message("r", 1, "ring").link_list(3)
