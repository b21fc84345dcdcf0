"""Exploration noise of fine-tuning: a draw held through an action chunk, and seeded pink noise, as SB3 ActionNoise."""

import gymnasium as gym
import numpy as np
import pytest
from rollouts import random_rollouts
from stable_baselines3.common.noise import ActionNoise, OrnsteinUhlenbeckActionNoise

from sb3_cql import CQL
from sb3_cql.common import HeldActionNoise, pink_action_noise


class Counting(ActionNoise):
    """Draws 1, 2, 3, ... (one per call) and counts its resets."""

    def __init__(self) -> None:
        super().__init__()
        self.draws, self.resets = 0, 0

    def __call__(self) -> np.ndarray:
        self.draws += 1
        return np.array([float(self.draws)])

    def reset(self) -> None:
        self.resets += 1


def test_a_held_draw_repeats_for_hold_calls_and_a_reset_draws_again():
    base = Counting()
    noise = HeldActionNoise(base, 3)
    assert [noise()[0] for _ in range(7)] == [1, 1, 1, 2, 2, 2, 3]
    noise.reset()
    assert base.resets == 1 and [noise()[0] for _ in range(4)] == [4, 4, 4, 5]  # a new draw at once after a reset
    assert [HeldActionNoise(Counting(), 1)()[0] for _ in range(2)] == [1, 1]  # hold 1: every call a draw of its own
    with pytest.raises(ValueError, match="hold must be >= 1, got 0"):
        HeldActionNoise(base, 0)


def test_a_held_draw_returned_is_a_copy_and_resets_the_noise_it_holds():
    ou = OrnsteinUhlenbeckActionNoise(np.zeros(2), np.full(2, 0.5))
    noise = HeldActionNoise(ou, 2)
    first = noise()
    first[:] = 99.0
    assert not (noise() == 99.0).any()
    noise.reset()
    assert (ou.noise_prev == 0).all()  # OU starts again from its mean


def test_pink_noise_is_seeded_has_the_scale_asked_and_is_correlated_in_time():
    draws = {seed: np.array([noise() for noise in [pink_action_noise(0.3, 2, 500, seed=seed)] for _ in range(500)])
             for seed in (1, 2)}  # fmt: skip
    again = pink_action_noise(0.3, 2, 500, seed=1)
    np.testing.assert_array_equal(draws[1], np.array([again() for _ in range(500)]))
    assert not np.array_equal(draws[1], draws[2])
    assert draws[1].shape == (500, 2) and 0.2 < draws[1].std() < 0.4
    assert np.corrcoef(draws[1][:-1, 0], draws[1][1:, 0])[0, 1] > 0.5
    with pytest.raises(ValueError, match="pink noise needs sigma >= 0"):
        pink_action_noise(-0.1, 2, 500)


def test_a_chunked_fine_tuning_draws_the_held_noise_once_per_chunk():
    """Pendulum's episodes are 200 steps: chunks of 3 and a draw held for 3 steps give 67 draws an episode, the
    last chunk cut at its end; 252 steps (84 trainings of train_freq 3): 67 + 18."""
    base = Counting()
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_rollouts(gym.make("Pendulum-v1"), 300), action_chunk=3,
                online_fraction=0.5, online_buffer_size=1000, batch_size=16, cql_n_actions=2, policy_kwargs={"net_arch": [16]},
                deterministic_rollouts=True, action_noise=HeldActionNoise(base, 3), train_freq=3, seed=0)  # fmt: skip
    model.learn(252)
    assert base.draws == 67 + 18 and base.resets == 2  # SB3's at learn's start, the first episode's end
    assert model._n_updates == 252 // 3  # one gradient step a chunk


def test_fine_tuning_with_the_same_seed_and_pink_noise_repeats():
    def stored_actions() -> np.ndarray:
        model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_rollouts(gym.make("Pendulum-v1"), 300), action_chunk=3,
                    online_fraction=0.5, batch_size=16, cql_n_actions=2, policy_kwargs={"net_arch": [16]},
                    online_buffer_size=100, deterministic_rollouts=True, train_freq=3,
                    action_noise=pink_action_noise(0.2, 1, 200, seed=5), seed=0)  # fmt: skip
        model.learn(30)
        return model.replay_buffer.online.actions[:30].copy()

    first = stored_actions()
    np.testing.assert_array_equal(first, stored_actions())
    assert np.abs(first).max() > 0
