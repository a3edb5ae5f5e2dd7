"""A signal a library catches (OSQP turns SIGINT during a solve into its status ``OSQP_SIGINT``)
is the command's interrupt, never a failed solve (:func:`infra.interrupt.caught_by_library`)."""

from __future__ import annotations

import signal

import pytest

from infra import interrupt


def test_with_the_handlers_it_is_the_interrupt_and_is_recorded() -> None:
    previous = interrupt.install()
    try:
        with pytest.raises(interrupt.Interrupted) as caught:
            interrupt.caught_by_library(signal.SIGINT)
        assert caught.value.signum == signal.SIGINT
        assert interrupt.received() == signal.SIGINT
    finally:
        interrupt.restore(previous)


def test_inside_held_it_is_only_recorded() -> None:
    previous = interrupt.install()
    try:
        with interrupt.held():
            interrupt.caught_by_library(signal.SIGINT)  # nothing raised inside the block
        assert interrupt.received() == signal.SIGINT
        with pytest.raises(interrupt.Interrupted):
            interrupt.raise_if_interrupted()
    finally:
        interrupt.restore(previous)


def test_without_the_handlers_it_is_a_keyboard_interrupt_and_nothing_is_kept() -> None:
    with pytest.raises(KeyboardInterrupt):
        interrupt.caught_by_library(signal.SIGINT)
    assert interrupt.received() is None

