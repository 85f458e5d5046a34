"""RL2DQN: recurrent dueling double DQN with trial sequence replay (the paper's RL² baseline)."""

import os

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor

import dream_envs
from dream_envs import EXPLORATION, TrialEnv
from sb3_dream.common.recurrent import (
    LinearEpsilonSchedule,
    double_dqn_targets,
    masked_td_loss,
    unroll_lstm,
)
from sb3_dream.common.wrappers import FinalObsWrapper, RL2ObservationWrapper
from sb3_dream.evaluation import evaluate_meta
from sb3_dream.rl2dqn import RL2DQN, recurrent_double_dqn_loss


class CueMemoryEnv(TrialEnv):
    """A 2-bit cue shown in the middle of exploration must be typed back, bit by bit, in execution.

    Four problems (cues 0..3); inner horizon 2; ``obs = [t, cue]``. Exploration shows ``1 + cue`` on
    its second step only (so it is in a returned observation, not only in ``final_obs``). Execution:
    actions in {0, 1}; reward 1 on the last step iff action t equals bit t of the cue.
    Optimal return 1; a feed-forward agent can carry at most one bit through ``prev_action`` (return
    at most 0.5); a random one gets 0.25.
    """

    def __init__(self, split="train", n_exec_episodes=1, render_mode=None, image=False):
        self.image = image
        obs_space = spaces.Box(0, 255, (32, 32, 3), np.uint8) if image else spaces.MultiDiscrete([3, 5])
        super().__init__(
            inner_observation_space=obs_space,
            instruction_nvec=[2],
            n_actions=2,
            end_episode_action=None,
            split=split,
            n_exec_episodes=n_exec_episodes,
            horizon=2,
            render_mode=render_mode,
        )

    @property
    def n_problems(self):
        return 4

    def _split_problem_ids(self, split):
        return np.arange(4)

    def _sample_instruction(self, problem_id, split):
        return np.array([1])

    def _set_problem(self, problem_id):
        self._bits = [(problem_id >> t) & 1 for t in range(2)]

    def _state(self, t, cue):
        if not self.image:
            return np.array([t, cue])
        img = np.zeros((32, 32, 3), np.uint8)
        img[:, :, 0] = 60 * t
        img[:16, :, 1] = 60 * cue
        return img

    def _inner_reset(self):
        self._t_inner, self._correct = 0, True
        return self._state(0, 0)

    def _inner_step(self, action):
        t = self._t_inner
        self._t_inner += 1
        if self.phase == EXPLORATION:
            return self._state(t + 1, 1 + self.problem_id if t == 0 else 0), 0.0, False
        self._correct &= action == self._bits[t]
        return self._state(t + 1, 0), float(self._correct) if t == 1 else 0.0, False

    def _render_frame(self):
        return np.zeros((8, 8, 3), np.uint8)


SMALL_NET = dict(lstm_hidden_size=16, fusion_dim=16, embed_kwargs=dict(per_dim=4, state_hidden_dims=(16, 16)))


def small_model(env, **kwargs):
    params = dict(learning_starts=20, buffer_size=200, batch_size=4, train_freq=1, seed=0, policy_kwargs=SMALL_NET)
    params.update(kwargs)
    return RL2DQN(params.pop("policy", "MultiInputLstmPolicy"), env, **params)


# ---------------------------------------------------------------------- construction and defaults
def test_paper_defaults_and_network_sizes():
    model = RL2DQN("MultiInputLstmPolicy", "MetaBandit-v0")
    assert isinstance(model.policy, RL2DQN.policy_aliases["MultiInputLstmPolicy"])
    assert (model.learning_rate, model.batch_size, model.gamma, model.max_grad_norm) == (1e-4, 32, 0.99, 10.0)
    assert (model.buffer_size, model.sequence_length, model.burn_in, model.stored_state) == (16_000, 50, 0, False)
    assert (model.target_update_interval, model.train_every, model.learning_starts) == (5000, 4, 16_000)
    sched = model.exploration_schedule
    assert (sched(0), sched(250_000), sched(500_000), sched(10**7)) == pytest.approx((1.0, 0.505, 0.01, 0.01))
    assert model.policy.optimizer.param_groups[0]["lr"] == 1e-4
    net = model.q_net
    emb = net.embedder.embedders
    assert set(emb.keys()) == {"obs", "instruction", "prev_action", "prev_reward", "episode_start"}
    assert emb["obs"].embedding.embedding_dim == 32 and emb["obs"].embed_dim == 64
    assert [m.out_features for m in emb["obs"].mlp if isinstance(m, th.nn.Linear)] == [256, 64]
    assert emb["instruction"].embed_dim == 64
    assert emb["prev_action"].embed_dim == emb["prev_reward"].embed_dim == emb["episode_start"].embed_dim == 16
    assert net.fusion[0].in_features == 64 + 64 + 16 * 3 and net.fusion[0].out_features == 64
    assert (net.lstm.input_size, net.lstm.hidden_size, net.lstm.num_layers) == (64, 64, 1)
    assert net.head.advantage.out_features == model.action_space.n and net.head.value.out_features == 1
    # the target network starts equal and is excluded from the optimizer
    for p, q in zip(model.q_net.parameters(), model.q_net_target.parameters()):
        assert th.equal(p, q) and not q.requires_grad
    n_opt = sum(p.numel() for g in model.policy.optimizer.param_groups for p in g["params"])
    assert n_opt == sum(p.numel() for p in model.q_net.parameters())


def test_metabus_constructs_with_and_without_policy_name():
    pytest.importorskip("dream_envs.bus")
    for model in (RL2DQN("MultiInputLstmPolicy", "MetaBus-v0"), RL2DQN("MetaBus-v0")):
        assert isinstance(model.policy, RL2DQN.policy_aliases["MultiInputLstmPolicy"])
        assert model.action_space.n == 9
    model = RL2DQN(gym.make("MetaBus-v0"))
    action, state = model.predict(model.env.reset(), deterministic=True)
    assert action.shape == (1,) and state[0].shape == (1, 1, 64)


def test_bad_input_errors():
    with pytest.raises(ValueError, match="Discrete action space"):
        RL2DQN(_BoxActionTrialEnv())
    with pytest.raises(ValueError, match="RL2ObservationWrapper"):
        RL2DQN(gym.make("CartPole-v1"))
    assert RL2DQN(RL2ObservationWrapper(gym.make("CartPole-v1"))).q_net.embedder.keys == [
        "obs",
        "prev_action",
        "prev_reward",
    ]
    with pytest.raises(ValueError, match="missing the key 'obs'"):
        RL2DQN(_DictEnv(spaces.Dict({"state": spaces.Discrete(3)})))
    with pytest.raises(ValueError, match="unsupported keys"):
        RL2DQN(_DictEnv(spaces.Dict({"obs": spaces.Discrete(3), "extra": spaces.Discrete(3)})))
    with pytest.raises(ValueError, match="prev_action"):
        RL2DQN(_DictEnv(spaces.Dict({"obs": spaces.Discrete(3), "prev_action": spaces.Box(0, 1, (1,))})))
    with pytest.raises(ValueError, match="sequence_length"):
        RL2DQN(CueMemoryEnv(), sequence_length=0)
    with pytest.raises(ValueError, match="burn_in"):
        RL2DQN(CueMemoryEnv(), sequence_length=5, burn_in=5)
    with pytest.raises(ValueError, match="td_loss='l1' is not valid; accepted values: 'mse', 'huber'"):
        RL2DQN(CueMemoryEnv(), td_loss="l1")
    with pytest.raises(ValueError, match="max_grad_norm must be a number >= 0"):
        RL2DQN(CueMemoryEnv(), max_grad_norm=-1)
    with pytest.raises(ValueError, match=r"tau must be in \[0, 1\]"):
        RL2DQN(CueMemoryEnv(), tau=2.0)
    with pytest.raises(ValueError, match="policy="):
        RL2DQN("MlpLstmPolicy", CueMemoryEnv())
    with pytest.raises(ValueError, match="CnnLstmPolicy needs an image"):
        RL2DQN("CnnLstmPolicy", CueMemoryEnv())
    with pytest.raises(ValueError, match="env is required"):
        RL2DQN("MultiInputLstmPolicy")
    with pytest.raises(ValueError, match="FinalObsWrapper"):
        RL2DQN(make_vec_env(CueMemoryEnv, n_envs=2), consume_final_obs=True)
    # works once wrapped
    RL2DQN(make_vec_env(CueMemoryEnv, n_envs=2, wrapper_class=FinalObsWrapper), consume_final_obs=True)
    model = small_model(CueMemoryEnv())
    with pytest.raises(ValueError, match="state must be"):
        model.predict(model.env.reset(), state=(np.zeros((1, 2, 16)), np.zeros((1, 2, 16))))
    with pytest.raises(ValueError, match="missing the keys"):
        model.predict({"obs": np.zeros(2, np.int64)})


class _DictEnv(gym.Env):
    def __init__(self, observation_space, action_space=None):
        self.observation_space = observation_space
        self.action_space = action_space or spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, True, False, {}


def _BoxActionTrialEnv():
    env = CueMemoryEnv()
    return _DictEnv(env.observation_space, spaces.Box(-1, 1, (1,)))


# ---------------------------------------------------------------------- targets and losses on hand-made tensors
def test_double_dqn_targets_use_online_argmax_and_target_values():
    next_online = th.tensor([[[1.0, 5.0, 2.0], [3.0, 0.0, 1.0]]])  # argmax 1, then 0
    next_target = th.tensor([[[10.0, 20.0, 30.0], [40.0, 50.0, 60.0]]])  # max would pick 2 both times
    rewards = th.tensor([[1.0, 2.0]])
    dones = th.tensor([[0.0, 1.0]])
    targets = double_dqn_targets(next_online, next_target, rewards, dones, gamma=0.5)
    assert th.allclose(targets, th.tensor([[1.0 + 0.5 * 20.0, 2.0]]))


def test_masked_td_loss_ignores_masked_steps():
    q = th.tensor([[1.0, 2.0, 100.0]])
    targets = th.tensor([[0.0, 4.0, -100.0]])
    mask = th.tensor([[1.0, 1.0, 0.0]])
    assert masked_td_loss(q, targets, mask, "mse").item() == pytest.approx((1.0 + 4.0) / 2)
    assert masked_td_loss(q, targets, mask, "huber").item() == pytest.approx((0.5 + 1.5) / 2)
    with pytest.raises(ValueError, match="td_loss"):
        masked_td_loss(q, targets, mask, "l1")


def test_sequence_loss_matches_hand_computation_and_ignores_padding():
    # 4-step trials cut in sequences of 3: chunks of 3 and 1 steps, so the batch has padding
    model = small_model(CueMemoryEnv(), learning_starts=0, sequence_length=3)
    model.learn(40)
    batch = model.replay_buffer._get_samples(np.array([0, 1, 2, 3]))
    assert batch.lengths.tolist() == [3, 1, 3, 1] and batch.actions.shape == (4, 3)
    loss, _ = recurrent_double_dqn_loss(model.q_net, model.q_net_target, batch, gamma=0.9)
    # hand computation, one sequence at a time, from the step-by-step network
    errors = []
    for b in range(4):
        n = int(batch.lengths[b])
        n_obs = n + 1
        obs = {k: v[[b], :n_obs] for k, v in batch.observations.items()}
        q_online, _ = model.q_net(obs, model.q_net.initial_states(1))
        q_target, _ = model.q_net_target(obs, model.q_net.initial_states(1))
        for t in range(n):
            a_star = int(q_online[0, t + 1].argmax())
            target = batch.rewards[b, t] + 0.9 * (1 - batch.dones[b, t]) * q_target[0, t + 1, a_star]
            errors.append((q_online[0, t, batch.actions[b, t]] - target) ** 2)
    assert loss.item() == pytest.approx(th.stack(errors).mean().item(), rel=1e-5)
    # garbage in the padding changes nothing
    padded = batch._replace(
        observations={
            k: th.where(_pad_mask(batch, v), v.max() if v.dtype != th.float32 else 7.0, v)
            for k, v in batch.observations.items()
        },
        rewards=th.where(batch.mask.bool(), batch.rewards, 99.0),
    )
    loss2, _ = recurrent_double_dqn_loss(model.q_net, model.q_net_target, padded, gamma=0.9)
    assert loss2.item() == pytest.approx(loss.item(), rel=1e-6)


def _pad_mask(batch, value):
    t = th.arange(value.shape[1])
    pad = t[None, :] > batch.lengths[:, None]  # observations 0..length are used
    return pad.view(*pad.shape, *([1] * (value.dim() - 2)))


def test_burn_in_cuts_the_gradient_of_masked_sequences_only():
    lstm = th.nn.LSTM(3, 4, batch_first=True)
    x = th.randn(2, 6, 3, requires_grad=True)
    h0 = (th.zeros(1, 2, 4), th.zeros(1, 2, 4))
    out, _ = unroll_lstm(lstm, x, h0, burn_in=2, burn_in_mask=th.tensor([True, False]))
    ref, _ = lstm(x, h0)
    assert th.allclose(out, ref, atol=1e-6)  # same values as one unroll
    out[:, 2:].sum().backward()
    assert th.all(x.grad[0, :2] == 0) and th.any(x.grad[0, 2:] != 0)
    assert th.any(x.grad[1, :2] != 0)


def test_epsilon_schedule():
    sched = LinearEpsilonSchedule(1.0, 0.1, 100)
    assert [sched(s) for s in (0, 50, 100, 1000)] == pytest.approx([1.0, 0.55, 0.1, 0.1])
    with pytest.raises(ValueError, match="exploration_final_eps"):
        LinearEpsilonSchedule(1.0, 1.5, 10)


# ---------------------------------------------------------------------- hidden state across trials
def test_hidden_state_kept_across_inner_episodes_and_reset_at_trial_start():
    env = CueMemoryEnv(n_exec_episodes=2)
    model = small_model(env)
    obs_list, obs, _ = [], *env.reset(seed=0)
    state, start, inner_starts = None, True, 0
    for _ in range(6):  # 3 inner episodes of 2 steps: one trial
        obs_list.append(obs)
        inner_starts += int(obs["episode_start"])
        _, state = model.predict(obs, state=state, episode_start=np.array([start]), deterministic=True)
        start = False
        obs, *_ = env.step(0)
    assert inner_starts == 3  # inner episode starts happened mid-trial...
    stacked = {k: th.as_tensor(np.stack([np.asarray(o[k]) for o in obs_list]))[None] for k in obs_list[0]}
    _, (h_ref, c_ref) = model.q_net(stacked, model.q_net.initial_states(1))
    # ... and the state equals one unroll of the whole trial from zeros: never reset in between
    assert np.allclose(state[0], h_ref.detach().numpy(), atol=1e-5)
    assert np.allclose(state[1], c_ref.detach().numpy(), atol=1e-5)
    # episode_start=True (a new trial) forgets everything
    _, fresh = model.predict(obs_list[0], state=None, episode_start=np.array([True]), deterministic=True)
    _, reset = model.predict(obs_list[0], state=state, episode_start=np.array([True]), deterministic=True)
    assert np.allclose(fresh[0], reset[0]) and not np.allclose(reset[0], state[0])


def test_vectorised_collection_resets_states_per_env_at_trial_starts_only():
    venv = make_vec_env(CueMemoryEnv, n_envs=3, env_kwargs=dict(n_exec_episodes=2), seed=1)
    model = small_model(venv, learning_starts=10_000)
    calls = []
    step = model.q_net.step

    def spy(obs, states, episode_start):
        q, inp, out = step(obs, states, episode_start)
        calls.append(
            (obs["episode_start"].clone(), states[0].clone(), episode_start.clone(), inp[0].clone(), out[0].clone())
        )
        return q, inp, out

    model.q_net.step = spy
    model.learn(60)
    assert len(calls) == 20  # one batched forward per vectorised step
    for k, (inner_start, h_in, trial_start, h_used, h_out) in enumerate(calls):
        # each trial lasts 6 steps in every env: trials start at steps 0, 6, 12, ...
        expected = th.full((3,), float(k % 6 == 0))
        assert th.equal(trial_start, expected)
        if k > 0:
            assert th.equal(h_in, calls[k - 1][4])  # the state is carried from the previous step
        for e in range(3):
            if trial_start[e]:
                assert th.all(h_used[0, e] == 0)
            else:
                assert th.equal(h_used[0, e], h_in[0, e])  # not reset at inner episode starts
    assert any(bool(c[0].any()) and not bool(c[2].any()) for c in calls)  # inner starts occurred mid-trial
    # every stored sequence is one whole trial: starts at a trial start, ends terminal
    buf = model.replay_buffer
    assert buf.size() == 9  # 3 envs x 3 finished trials
    np.testing.assert_array_equal(buf.lengths[:9], 6)
    assert np.all(buf.observations["prev_action"][:9, 0] == 0)
    assert np.all(buf.dones[:9, 5] == 1) and not buf.dones[:9, :5].any()


def test_stored_states_and_burn_in_chunks_match_the_actor():
    # 6-step trials in sequences of 3 with 1 burn-in step: chunks hold steps 0-2, 2-4 and 4-5
    model = small_model(
        CueMemoryEnv(n_exec_episodes=2), learning_starts=10_000, sequence_length=3, burn_in=1, stored_state=True
    )
    model.learn(6)  # one trial, no update: q_net is the network that acted
    buf = model.replay_buffer
    assert buf.size() == 3 and list(buf.lengths[:3]) == [3, 3, 2] and list(buf.train_from[:3]) == [0, 1, 1]
    rows = {k: buf.observations[k] for k in buf.keys}
    # the trial's 7 observations (6 steps + the terminal one), rebuilt from the overlapping chunks
    trial = {k: th.as_tensor(np.concatenate([v[0, :3], v[1, 1:4], v[2, 2:3]]))[None] for k, v in rows.items()}
    q_trial, _ = model.q_net(trial, model.q_net.initial_states(1))
    for row, first in ((1, 2), (2, 4)):
        prefix = {k: v[:, :first] for k, v in trial.items()}
        _, (h, c) = model.q_net(prefix, model.q_net.initial_states(1))
        # the stored state is the actor's state on the chunk's first step
        assert np.allclose(buf.states[row, 0], h[:, 0].detach().numpy(), atol=1e-5)
        assert np.allclose(buf.states[row, 1], c[:, 0].detach().numpy(), atol=1e-5)
        # so the chunk's own unroll from it reproduces the whole trial's Q-values
        n_obs = int(buf.lengths[row]) + 1
        chunk = {k: th.as_tensor(v[[row], :n_obs]) for k, v in rows.items()}
        stored = tuple(th.as_tensor(buf.states[[row], i]).transpose(0, 1).contiguous() for i in (0, 1))
        q_chunk, _ = model.q_net(chunk, stored)
        last = first + n_obs
        assert th.allclose(q_chunk, q_trial[:, first:last], atol=1e-5)
    batch = buf._get_samples(np.arange(3))
    assert batch.burn_in_mask.tolist() == [False, True, True]
    assert batch.mask.tolist() == [[1, 1, 1], [0, 1, 1], [0, 1, 0]]


def test_train_freq_counts_env_steps_over_envs():
    venv = make_vec_env(CueMemoryEnv, n_envs=4, seed=0)
    model = small_model(venv, learning_starts=0, train_freq=4, gradient_steps=2)
    model.learn(200)
    # 50 vectorised steps = 200 env steps -> 2 updates per 4 env steps, once the first trials
    # (4 steps) are in the buffer: 2 x 47
    assert model._n_updates == 94


# ---------------------------------------------------------------------- SB3 integration
def test_save_load_identical_predictions_and_replay_buffer(tmp_path):
    model = small_model(CueMemoryEnv(), learning_starts=10)
    model.learn(60)
    path = tmp_path / "rl2dqn.zip"
    model.save(path)
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    loaded = RL2DQN.load(path, env=make_vec_env(CueMemoryEnv, n_envs=2))  # a different number of envs
    env = CueMemoryEnv(n_exec_episodes=2)
    obs, _ = env.reset(seed=3)
    s1 = s2 = None
    for t in range(6):
        a1, s1 = model.predict(obs, s1, np.array([t == 0]), deterministic=True)
        a2, s2 = loaded.predict(obs, s2, np.array([t == 0]), deterministic=True)
        assert a1 == a2 and np.array_equal(s1[0], s2[0]) and np.array_equal(s1[1], s2[1])
        obs, *_ = env.step(int(a1))
    assert loaded.sequence_length == model.sequence_length and loaded._n_updates == model._n_updates
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    assert loaded.replay_buffer.size() == model.replay_buffer.size()
    np.testing.assert_array_equal(loaded.replay_buffer.actions, model.replay_buffer.actions)
    loaded.learn(40, reset_num_timesteps=False)  # training goes on from the loaded buffer, now with 2 envs
    assert loaded.replay_buffer.size() > model.replay_buffer.size() and loaded._n_updates > model._n_updates
    with pytest.raises(ValueError, match="spaces do not match"):
        RL2DQN.load(path, env=dream_envs_bandit())


def dream_envs_bandit():
    return gym.make("MetaBandit-v0", n_actions=3)


def test_callbacks_evaluate_policy_logging(tmp_path):
    model = small_model(CueMemoryEnv(), learning_starts=10, tensorboard_log=str(tmp_path / "tb"))
    eval_cb = EvalCallback(Monitor(CueMemoryEnv()), n_eval_episodes=3, eval_freq=40, log_path=str(tmp_path / "eval"))
    ckpt_cb = CheckpointCallback(save_freq=50, save_path=str(tmp_path / "ckpt"), name_prefix="rl2")
    model.learn(100, callback=[eval_cb, ckpt_cb], progress_bar=True, log_interval=1)
    assert os.path.exists(tmp_path / "eval" / "evaluations.npz") and eval_cb.best_mean_reward > -np.inf
    assert os.listdir(tmp_path / "ckpt") and RL2DQN.load(tmp_path / "ckpt" / "rl2_50_steps.zip")
    assert any(f.startswith("events") for _, _, fs in os.walk(tmp_path / "tb") for f in fs)
    mean, std = evaluate_policy(model, make_vec_env(CueMemoryEnv, n_envs=2), n_eval_episodes=4)
    assert 0.0 <= mean <= 1.0
    # logger keys follow SB3
    model.set_logger(configure(str(tmp_path / "csv"), ["csv"]))
    model.learn(60, reset_num_timesteps=False, log_interval=1)
    header = open(tmp_path / "csv" / "progress.csv").readline().strip().split(",")
    for key in (
        "train/loss",
        "train/q_mean",
        "train/n_updates",
        "rollout/exploration_rate",
        "rollout/ep_rew_mean",
        "time/fps",
    ):
        assert key in header


def test_cnn_lstm_policy_on_image_trials():
    venv = make_vec_env(CueMemoryEnv, n_envs=2, env_kwargs=dict(image=True))
    model = small_model(venv, policy="CnnLstmPolicy", learning_starts=8)
    cnn = model.q_net.embedder.embedders["obs"]
    assert [c.kernel_size[0] for c in cnn.cnn if isinstance(c, th.nn.Conv2d)] == [5, 5, 4]
    assert all(c.stride == (2, 2) and c.out_channels == 32 for c in cnn.cnn if isinstance(c, th.nn.Conv2d))
    assert cnn.embed_dim == 128
    model.learn(40)
    assert model.replay_buffer.observations["obs"].shape[2:] == (3, 32, 32)  # stored channel-first
    # channel-last observations straight from the env work in predict
    obs, _ = CueMemoryEnv(image=True).reset(seed=0)
    action, state = model.predict(obs, deterministic=True)
    assert action.shape == () and state[0].shape == (1, 1, 16)


def test_final_obs_is_consumed_when_asked():
    env = FinalObsWrapper(gym.make("MetaBandit-v0", n_actions=2, horizon=1))
    obs, _ = env.reset(seed=0)
    assert not obs["final_obs"].any()
    obs, _, _, _, info = env.step(0)  # action 0 in exploration reveals the problem in the last state
    assert info["episode_end"] and np.array_equal(obs["final_obs"], info["final_obs"]) and obs["final_obs"][-1] >= 1
    model = small_model(gym.make("MetaBandit-v0", n_actions=2, horizon=1), consume_final_obs=True)
    assert "final_obs" in model.observation_space.spaces and model.q_net.embedder.use_final_obs
    model.learn(30)
    assert model.replay_buffer.observations["final_obs"][: model.replay_buffer.size()].any()
    # the trial agent builds the key from info on a bare env (as evaluate_meta plays it)
    result = dream_envs.play_trial(gym.make("MetaBandit-v0", n_actions=2, horizon=1), model.as_trial_agent())
    assert len(result["execution_returns"]) == 1


@pytest.mark.parametrize("consume_final_obs", [False, True])
def test_trials_side_by_side_are_the_trials_played_one_at_a_time(consume_final_obs, played_side_by_side):
    model = small_model(gym.make("MetaBus-v0"), consume_final_obs=consume_final_obs)
    generator = th.Generator().manual_seed(0)
    with th.no_grad():  # weights that make the actions depend on the observations (a fresh model's do not)
        for p in model.policy.parameters():
            p.copy_(th.randn(p.shape, generator=generator))
    actions = played_side_by_side(model, "MetaBus-v0", n_trials=11, n_envs=4)
    assert len({tuple(a) for a in actions.values()}) > 1  # the trials differ


def test_zero_exploration_rewards():
    env = gym.make("MetaBandit-v0", n_actions=2, horizon=1, reward_free_exploration=False)
    model = small_model(env, zero_exploration_rewards=True, learning_starts=1000)
    model.learn(200)
    buf = model.replay_buffer
    n = buf.size()
    phase = buf.observations["phase"][:n, :2]
    assert np.all(buf.rewards[:n, :2][phase == 0] == 0)
    assert buf.rewards[:n, :2][phase == 1].any()  # execution rewards are kept


# ---------------------------------------------------------------------- learning
@pytest.mark.slow
def test_rl2dqn_solves_a_memory_task_that_feedforward_dqn_cannot():
    """The cue is visible only mid-exploration: RL2DQN must carry it in its LSTM."""
    params = dict(
        learning_starts=500,
        train_freq=1,
        target_update_interval=200,
        learning_rate=1e-3,
        buffer_size=2000,
        seed=0,
    )
    model = RL2DQN(
        make_vec_env(CueMemoryEnv, n_envs=2, seed=0),
        exploration_steps=2000,
        exploration_final_eps=0.05,
        policy_kwargs=dict(
            lstm_hidden_size=32,
            fusion_dim=32,
            embed_kwargs=dict(per_dim=8, state_hidden_dims=(32, 32), instruction_embed_dim=8),
        ),
        **params,
    )
    model.learn(4000)
    rl2_return, _ = evaluate_policy(model, make_vec_env(CueMemoryEnv, n_envs=4, seed=1), n_eval_episodes=200)
    assert rl2_return >= 0.9

    ff = DQN("MultiInputPolicy", CueMemoryEnv(), exploration_fraction=0.5, exploration_final_eps=0.05, **params)
    ff.learn(4000)
    ff_return, _ = evaluate_policy(ff, make_vec_env(CueMemoryEnv, n_envs=4, seed=1), n_eval_episodes=200)
    assert ff_return <= 0.6  # at most one of the two bits survives without memory


@pytest.mark.slow
def test_rl2dqn_consuming_final_obs_solves_the_bandit():
    """MetaBandit-v0 (|A| = 2, H = 1): the reveal is only in the exploration episode's last state,
    which RL2DQN sees with ``consume_final_obs`` (without it, it stays at chance, 0.5)."""
    kwargs = dict(n_actions=2, horizon=1)
    model = RL2DQN(
        make_vec_env("MetaBandit-v0", n_envs=2, seed=0, env_kwargs=kwargs, wrapper_class=FinalObsWrapper),
        consume_final_obs=True,
        learning_starts=500,
        train_freq=1,
        exploration_steps=2000,
        exploration_final_eps=0.05,
        target_update_interval=200,
        learning_rate=1e-3,
        buffer_size=2000,
        seed=0,
        policy_kwargs=dict(
            lstm_hidden_size=32,
            fusion_dim=32,
            embed_kwargs=dict(per_dim=8, state_hidden_dims=(32, 32), instruction_embed_dim=8),
        ),
    )
    model.learn(3000)
    # played on bare trial envs: the trial agent builds final_obs from info
    result = evaluate_meta(model, "MetaBandit-v0", n_trials=100, split="test", env_kwargs=kwargs)
    assert result.mean >= 0.9
    assert result.mean_exploration_length == 1.0


def test_sb3_argument_names_keep_sb3s_meaning():
    model = RL2DQN("MetaBus-v0", seed=0, learning_starts=200, buffer_size=50, train_freq=(4, "step"))
    assert (model.learning_starts, model.train_every, model.gradient_steps) == (200, 4, 1)
    model.learn(200)
    assert model._n_updates == 0  # none before learning_starts env steps
    model.learn(200, reset_num_timesteps=False)
    assert model._n_updates == 50  # then gradient_steps per train_freq env steps
    with pytest.raises(ValueError, match="SB3's 'exploration_fraction'.*exploration_steps"):
        RL2DQN("MetaBus-v0", exploration_fraction=0.1)
    with pytest.raises(TypeError, match="learnin_starts"):
        RL2DQN("MetaBus-v0", learnin_starts=100)


@pytest.mark.parametrize("algo", ["DREAM", "RL2DQN", "IMPORT", "VariBAD"])
def test_adam_runs_fused_unless_optimizer_kwargs_choose(tmp_path, algo):
    import sb3_dream

    cls = getattr(sb3_dream, algo)
    quick = sb3_dream.PRESETS["fast"] if algo == "DREAM" else {"learning_starts": 20}
    model = cls("MetaBandit-v0", seed=0, **quick)
    optimizers = [model.policy.optimizer] + ([model.policy.exploration_optimizer] if algo == "DREAM" else [])
    for optimizer in optimizers:
        assert isinstance(optimizer, th.optim.Adam) and optimizer.param_groups[0]["fused"] is True
    model.learn(300 if algo == "DREAM" else 60)
    assert model._n_updates > 0
    model.save(tmp_path / "fused.zip")
    assert cls.load(tmp_path / "fused.zip").policy.optimizer.param_groups[0]["fused"] is True
    for kwargs in ({"fused": False}, {"foreach": True}):  # the per-parameter loop, the multi-tensor one
        chosen = cls("MetaBandit-v0", policy_kwargs={"optimizer_kwargs": kwargs}).policy.optimizer.param_groups[0]
        assert not chosen["fused"] and chosen["foreach"] == kwargs.get("foreach")
    sgd = cls("MetaBandit-v0", policy_kwargs={"optimizer_class": th.optim.SGD, "optimizer_kwargs": {"momentum": 0.9}})
    assert "fused" not in sgd.policy.optimizer_kwargs  # only Adam gets the fused default
