"""sb3_dream.DREAM: the math on hand-made tensors, the z sources, privacy, save/load, learning."""

from __future__ import annotations

import copy
import json
import pathlib
import pickle
import zipfile

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_dream import DREAM, MetaEvalCallback
from sb3_dream.dream import losses, updates
from sb3_dream.dream.dream import EXECUTION_TARGET_Z
from sb3_dream.dream.policies import DreamPolicy, TrajectoryDecoder
from sb3_dream.evaluation import as_trial_agent, evaluate_meta

FAST = dict(
    exploration_learning_starts=20,
    execution_learning_starts=20,
    eps_decay_steps=1000,
    target_update_interval=100,
    buffer_size=500,
    execution_buffer_size=2000,
)


@pytest.fixture(scope="module")
def bus_model():
    model = DREAM("MetaBus-v0", seed=0, **FAST)
    model.learn(600)
    return model


def test_defaults_are_the_papers():
    model = DREAM("MetaBandit-v0")
    assert (model.learning_rate, model.batch_size, model.gamma, model.train_every) == (1e-4, 32, 0.99, 4)
    assert (model.learning_starts, model.gradient_steps) == (0, 1)
    assert (model.target_update_interval, model.max_grad_norm, model.eps_decay_steps) == (5000, 10.0, 250_000)
    assert (model.buffer_size, model.execution_buffer_size) == (16_000, 100_000)
    assert (model.reward_penalty, model.encoder_variance, model.bottleneck_weight) == (0.01, 0.1, 1.0)
    assert model.bottleneck and model.bottleneck_threshold == 10.0 and model.z_dim == 64
    assert model.exploration_epsilon == 1.0 == model.execution_epsilon


def test_execution_epsilon_can_have_its_own_schedule(tmp_path):
    shared = DREAM("MetaBandit-v0", eps_decay_steps=1000, exploration_final_eps=0.05)
    shared._n_exploration_steps = shared._n_execution_steps = 2000
    assert shared.exploration_epsilon == 0.05 == shared.execution_epsilon  # the paper's: one schedule

    model = DREAM(
        "MetaBandit-v0", eps_decay_steps=1000, exploration_final_eps=0.05,
        execution_final_eps=0.2, execution_eps_decay_steps=100,
    )  # fmt: skip
    model._n_exploration_steps = model._n_execution_steps = 50
    assert model.exploration_epsilon == pytest.approx(1.0 - 0.95 * 0.05)
    assert model.execution_epsilon == pytest.approx(1.0 - 0.8 * 0.5)
    model._n_exploration_steps = model._n_execution_steps = 2000
    assert (model.exploration_epsilon, model.execution_epsilon) == (0.05, 0.2)
    model.save(tmp_path / "model.zip")
    loaded = DREAM.load(tmp_path / "model.zip")
    assert (loaded.exploration_epsilon, loaded.execution_epsilon) == (0.05, 0.2)
    with pytest.raises(ValueError, match="execution_final_eps must be in"):
        DREAM("MetaBandit-v0", execution_final_eps=1.5)
    with pytest.raises(ValueError, match="execution_eps_decay_steps must be >= 0"):
        DREAM("MetaBandit-v0", execution_eps_decay_steps=-1)


def test_exploration_reward_is_the_information_gain():
    model = DREAM("MetaBandit-v0", reward_penalty=0.01)
    f = th.tensor([[1.0, 0.0]])
    # prefixes 0..3 of a 3-transition trajectory, padded to 4 transitions
    g = th.tensor([[[0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [1.0, 1.0], [9.0, 9.0]]])
    r = model.exploration_rewards(g, f, lengths=th.tensor([3]))
    # d = [1, 0.25, 0, 1, -]: r_t = d_t - d_{t+1} - c; no reward past the trajectory's end
    np.testing.assert_allclose(r.numpy(), [[0.75 - 0.01, 0.25 - 0.01, -1.0 - 0.01, 0.0]], atol=1e-6)


def test_bottleneck_only_pushes_norms_above_k():
    model = DREAM("MetaBandit-v0", bottleneck_threshold=10.0)
    f = th.tensor([[1.0, 2.0], [3.0, 3.0]], requires_grad=True)  # ||f||^2 = 5 (< K) and 18 (> K)
    loss = losses.bottleneck_loss(f, model.bottleneck_threshold)
    loss.backward()
    assert loss.item() == pytest.approx((10.0 + 18.0) / 2)
    np.testing.assert_allclose(f.grad.numpy(), [[0.0, 0.0], [3.0, 3.0]])  # d/df of mean(||f||^2) on row 2 only
    no_bottleneck = DREAM("MetaBus-v0", bottleneck=False, seed=0, **FAST)
    no_bottleneck.learn(300)
    exe, traj = no_bottleneck.replay_buffer.sample_execution(4, no_bottleneck._rng)
    assert updates.execution_update(no_bottleneck, exe, traj)["bottleneck_loss"] == 0.0


def test_decoder_gives_every_prefix_in_one_pass_and_ignores_padding():
    decoder = TrajectoryDecoder(gym.spaces.MultiDiscrete([9, 9, 5]), n_actions=9)
    states = th.randint(0, 5, (2, 5, 3))
    actions = th.randint(0, 9, (2, 4))
    g = decoder(states, actions)
    assert g.shape == (2, 5, 64)
    # prefix t only depends on the first t transitions: changing later steps leaves it unchanged
    states2, actions2 = states.clone(), actions.clone()
    states2[:, 3:], actions2[:, 2:] = 0, 8
    g2 = decoder(states2, actions2)
    th.testing.assert_close(g[:, :3], g2[:, :3])
    assert not th.allclose(g[:, 4], g2[:, 4])
    # the empty prefix is the same for every trajectory
    th.testing.assert_close(g[0, 0], g[1, 0])
    # with lengths, only each trajectory's own prefix: the same values as indexing every prefix
    lengths = th.tensor([4, 2])
    th.testing.assert_close(decoder(states, actions, lengths), g[th.arange(2), lengths])


def test_z_sources_alternate_across_trials():
    model = DREAM("MetaBandit-v0", seed=0, **FAST)
    sources = []
    original = model.end_exploration

    def spy(state, idx, final_obs, problem_ids=None):
        sources.append(bool(model._z_from_encoder[idx[0]]))
        return original(state, idx, final_obs, problem_ids)

    model.end_exploration = spy
    model.learn(40)  # bandit trials are 2 steps
    assert len(sources) >= 15
    assert all(a != b for a, b in zip(sources, sources[1:]))


def test_f_source_z_is_noisy_around_f_and_g_source_is_the_decoder():
    model = DREAM("MetaBandit-v0", seed=0)
    pid = np.array([3, 3, 3, 3])
    z = model.encode(pid, noisy=True)
    f = model.encode(pid, noisy=False)
    assert np.allclose(f, f[0]) and not np.allclose(z, z[0])
    assert np.std(z - f) == pytest.approx(np.sqrt(0.1), rel=0.25)
    # a seeded generator gives the same noise (diagnose's noisy-code run), the global one goes on
    seeded = [model.encode(pid, noisy=True, generator=th.Generator().manual_seed(5)) for _ in range(2)]
    np.testing.assert_array_equal(seeded[0], seeded[1])
    assert not np.allclose(seeded[0], z) and np.std(seeded[0] - f) == pytest.approx(np.sqrt(0.1), rel=0.25)
    no_bottleneck = DREAM("MetaBandit-v0", bottleneck=False, seed=0)
    np.testing.assert_array_equal(no_bottleneck.encode(pid, noisy=True), no_bottleneck.encode(pid, noisy=False))


class ScrambleProblemId(gym.Wrapper):
    """Replaces info['problem_id'] with a random number: a model must not care."""

    def __init__(self, env, seed):
        super().__init__(env)
        self.rng = np.random.default_rng(seed)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return obs, {**info, "problem_id": int(self.rng.integers(1000))}

    def step(self, action):
        obs, r, term, trunc, info = self.env.step(action)
        return obs, r, term, trunc, {**info, "problem_id": int(self.rng.integers(1000))}


def test_no_problem_id_reaches_the_networks_at_meta_test(bus_model):
    results = []
    for seed in (1, 2):
        env = ScrambleProblemId(gym.make("MetaBus-v0", split="test"), seed)
        r = evaluate_meta(bus_model, env, n_trials=10, split="test", seed=5)
        results.append(r.returns)
        # and side by side in several scrambled envs
        envs = [ScrambleProblemId(gym.make("MetaBus-v0", split="test"), seed + k) for k in range(3)]
        results.append(evaluate_meta(bus_model, envs, n_trials=10, split="test", seed=5).returns)
    for returns in results[1:]:
        np.testing.assert_array_equal(results[0], returns)
    # and predict() gives the same actions whatever the problem, given the same observations
    env = gym.make("MetaBus-v0")
    obs, _ = env.reset(seed=0, options={"problem_id": 0})
    a1, _ = bus_model.predict(obs, deterministic=True)
    obs2, _ = env.reset(seed=0, options={"problem_id": 11})
    a2, _ = bus_model.predict(obs2, deterministic=True)
    assert a1 == a2


def test_trials_side_by_side_are_the_trials_played_one_at_a_time(bus_model, played_side_by_side):
    actions = played_side_by_side(bus_model, "MetaBus-v0", n_trials=13, n_envs=4)
    assert len({tuple(a) for a in actions.values()}) > 1  # the trials differ


def test_a_seed_reproduces_training_and_evaluating_on_the_way_changes_nothing():
    def trained(callback):
        model = DREAM("MetaBus-v0", seed=0, **FAST)
        model.learn(800, callback=callback)
        assert model._n_updates > 50
        return th.cat([p.detach().flatten() for p in model.policy.parameters()])

    alone = trained(None)
    assert th.equal(alone, trained(None))
    # meta-test evaluations in between, trials side by side, draw from no generator training uses
    assert th.equal(alone, trained(MetaEvalCallback("MetaBus-v0", eval_freq=300, n_trials=20, n_envs=8)))


def test_predict_state_follows_the_recurrent_convention(bus_model):
    vec = make_vec_env("MetaBus-v0", n_envs=3, seed=0)
    obs = vec.reset()
    actions, state = bus_model.predict(obs, deterministic=True)
    assert actions.shape == (3,) and isinstance(state, tuple)
    starts = np.zeros(3, bool)
    for _ in range(30):
        obs, _, dones, _ = vec.step(actions)
        actions, state = bus_model.predict(obs, state=state, episode_start=dones | starts, deterministic=True)
    mean, _ = evaluate_policy(bus_model, gym.make("MetaBus-v0"), n_eval_episodes=3)
    assert -2.5 <= mean <= 1.0


def test_training_mode_reaches_every_online_network(bus_model):
    policy = bus_model.policy
    policy.set_training_mode(True)
    assert policy.training and all(net.training for net in policy.onlines())
    policy.set_training_mode(False)
    assert not policy.training and not any(net.training for net in policy.onlines())
    policy.execution_q.train(True)  # a network switched on its own is switched back, not skipped
    policy.set_training_mode(False)
    assert not policy.execution_q.training


def test_save_load_round_trip(bus_model, tmp_path):
    bus_model.save(tmp_path / "dream.zip")
    loaded = DREAM.load(tmp_path / "dream.zip")
    assert loaded._n_trials == bus_model._n_trials and loaded._n_updates == bus_model._n_updates
    np.testing.assert_array_equal(loaded.problem_table, bus_model.problem_table)
    a = evaluate_meta(bus_model, "MetaBus-v0", n_trials=8, seed=3)
    b = evaluate_meta(loaded, "MetaBus-v0", n_trials=8, seed=3)
    np.testing.assert_array_equal(a.returns, b.returns)
    bus_model.save_replay_buffer(tmp_path / "buffer.pkl")
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    assert len(loaded.replay_buffer.exploration) == len(bus_model.replay_buffer.exploration)
    resumed = DREAM.load(tmp_path / "dream.zip", env=make_vec_env("MetaBus-v0", n_envs=2))
    resumed.load_replay_buffer(tmp_path / "buffer.pkl")
    steps = resumed.num_timesteps
    resumed.learn(100, reset_num_timesteps=False)  # training resumes where it stopped
    assert resumed.num_timesteps >= steps + 100 and resumed._n_updates > bus_model._n_updates


def test_resume_without_replay_buffer(bus_model, tmp_path):
    # The trial counter is restored but the buffers start empty: updates wait for new data.
    bus_model.save(tmp_path / "dream.zip")
    resumed = DREAM.load(tmp_path / "dream.zip", env=make_vec_env("MetaBus-v0", n_envs=2))
    assert len(resumed.replay_buffer.exploration) == 0 and resumed._n_trials > 0
    resumed.train(gradient_steps=1, batch_size=8)  # nothing to sample yet: no update, no error
    assert resumed._n_updates == bus_model._n_updates
    resumed.learn(200, reset_num_timesteps=False)
    assert len(resumed.replay_buffer.exploration) > 0 and resumed._n_updates > bus_model._n_updates


def test_vectorised_training_logs_dream_scalars(tmp_path):
    from stable_baselines3.common.logger import configure

    model = DREAM(make_vec_env("MetaBus-v0", n_envs=4, seed=0), seed=0, **FAST)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(1200, log_interval=10)
    assert model.num_timesteps >= 1200 and model._n_updates > 0
    header = (tmp_path / "progress.csv").read_text().splitlines()[0]
    for key in (
        "rollout/exploration_length",
        "rollout/execution_return_z_f",
        "rollout/execution_return_z_g",
        "train/exploration_reward",
        "train/decoder_loss",
        "train/f_norm_sq",
    ):
        assert key in header


@pytest.mark.parametrize("bootstrap", [False, True])
def test_horizon_cut_execution_steps_are_terminal_unless_bootstrapping(bootstrap):
    env = make_vec_env("MetaBus-v0", n_envs=1, seed=0, env_kwargs={"horizon": 3})
    model = DREAM(env, seed=0, bootstrap_at_horizon=bootstrap, **FAST)
    model.learn(60)
    buf = model.replay_buffer.execution
    terminals = int(buf.dones[: len(buf)].sum())
    # horizon 3 is too short to reach a goal: every execution episode ends by the horizon or by the
    # end-episode action (always terminal); one execution episode per finished trial
    if bootstrap:
        assert 0 <= terminals < model._episode_num
    else:
        assert terminals == model._episode_num > 10


@pytest.mark.opengl
def test_image_trials_train_and_meta_test():
    """SignNav3D: SB3 stores images channel-first, the env and info["final_obs"] give them channel-last."""
    small = dict(exploration_learning_starts=2, execution_learning_starts=2, buffer_size=20, execution_buffer_size=200)
    model = DREAM("SignNav3D-v0", seed=0, batch_size=4, **small)
    assert model.observation_space["obs"].shape == (3, 60, 80)
    model.learn(40)
    assert model._n_updates > 0
    result = evaluate_meta(model, "SignNav3D-v0", n_trials=1)
    assert result.returns.shape == (1, 1) and -1.0 <= result.mean <= 1.0


def test_decoder_hidden_size_sets_the_decoders_lstm_learns_and_is_saved(tmp_path):
    model = DREAM("MetaBus-v0", seed=0, policy_kwargs=dict(decoder_hidden_size=48), **FAST)
    for decoder in (model.policy.decoder, model.policy.decoder_target):
        assert decoder.lstm.hidden_size == 48 and decoder.head[0].in_features == 48
    assert model.policy.encoder.out.out_features == model.policy.decoder.head[-1].out_features == 64  # z_dim kept
    before = model.policy.decoder.lstm.weight_hh_l0.clone()
    model.learn(400)
    assert model._n_updates > 0 and not th.equal(before, model.policy.decoder.lstm.weight_hh_l0)
    model.save(tmp_path / "m.zip")
    loaded = DREAM.load(tmp_path / "m.zip")
    assert loaded.policy.decoder_hidden_size == 48 and loaded.policy.decoder.lstm.hidden_size == 48
    assert DREAM("MetaBus-v0").policy.decoder.lstm.hidden_size == 128  # the paper's decoder by default
    for bad in (0, 64.0, True):
        with pytest.raises(ValueError, match=f"decoder_hidden_size must be an integer >= 1, got {bad!r}"):
            DREAM("MetaBus-v0", policy_kwargs=dict(decoder_hidden_size=bad))


@pytest.mark.opengl
def test_image_downsample_pools_every_networks_frames_and_is_saved(tmp_path):
    small = dict(exploration_learning_starts=2, execution_learning_starts=2, buffer_size=20, execution_buffer_size=200)
    model = DREAM("SignNav3D-v0", seed=0, batch_size=4, policy_kwargs=dict(image_downsample=2), **small)
    sizes = []
    for net in (model.policy.decoder, model.policy.execution_q, model.policy.exploration_q):
        net.state_embed.cnn.register_forward_hook(lambda m, i, o: sizes.append(tuple(i[0].shape[-2:])))
    model.learn(40)
    assert model._n_updates > 0 and sizes and set(sizes) == {(30, 40)}  # 60 x 80 frames, pooled 2x2
    model.save(tmp_path / "m.zip")
    loaded = DREAM.load(tmp_path / "m.zip")
    assert loaded.policy.image_downsample == 2
    assert all(th.equal(a, b) for a, b in zip(model.policy.state_dict().values(), loaded.policy.state_dict().values()))
    with pytest.raises(ValueError, match="image_downsample=2 applies to image observations only"):
        DREAM("MetaBus-v0", policy_kwargs=dict(image_downsample=2))
    with pytest.raises(ValueError, match="image_downsample must be an integer >= 1, got True"):
        DREAM("SignNav3D-v0", policy_kwargs=dict(image_downsample=True))


@pytest.mark.parametrize("parallel", [False, True])
def test_decoder_and_bottleneck_learn_from_the_execution_samples_only(parallel):
    # Appendix A: f and g are updated "from the same execution replay buffer samples"; on the
    # exploration samples they only give the rewards (targets, no gradient).
    model = DREAM("MetaBus-v0", seed=1, parallel_updates=parallel, **FAST)
    model.learn(300)
    policy, calls = model.policy, []
    for name, net in [("g", policy.decoder), ("f", policy.encoder)]:
        net.register_forward_hook(lambda m, i, o, name=name: calls.append((name, i[0].shape[0], o.requires_grad)))
    before = [p.detach().clone() for p in policy.decoder.parameters()]
    model._update(8, exploration_ready=True, execution_ready=False)
    assert calls == [("g", 8, False), ("f", 8, False)]
    assert all(th.equal(a, b) for a, b in zip(before, policy.decoder.parameters()))
    calls.clear()
    model._update(8, exploration_ready=True, execution_ready=True)
    expected = [("g", 8, False), ("f", 8, False), ("g", 8, True), ("f", 8, True)]
    # with parallel updates the reward pass runs in the second thread beside the execution losses
    assert (sorted(calls) == sorted(expected)) if parallel else (calls == expected)
    assert not all(th.equal(a, b) for a, b in zip(before, policy.decoder.parameters()))


@pytest.mark.parametrize("choice", ["own", "encoder"])
def test_execution_target_z_picks_what_the_target_q_conditions_on(choice, tmp_path):
    model = DREAM("MetaBus-v0", seed=1, execution_target_z=choice, **FAST)
    model.learn(300)
    policy, decoder_calls, target_z = model.policy, [], []
    policy.decoder_target.register_forward_hook(lambda m, i, o: decoder_calls.append(o.shape))
    q_values = policy.execution_q_target.q_values
    policy.execution_q_target.q_values = lambda e, z: target_z.append(z) or q_values(e, z)
    model._update(8, exploration_ready=False, execution_ready=True)
    (z,) = target_z
    if choice == "own":  # rows [0, 8) from the target decoder, [8, 16) from the target encoder
        assert len(decoder_calls) == 1 and not th.allclose(z[:8], z[8:])
    else:  # the authors' code: the target encoder's f for both losses, no decoder pass
        assert decoder_calls == [] and th.equal(z[:8], z[8:])
    model.save(tmp_path / "model.zip")
    assert DREAM.load(tmp_path / "model.zip").execution_target_z == choice


def test_execution_target_z_rejects_other_values():
    accepted = "execution_target_z='decoder' is not valid; accepted values: 'own', 'encoder'"
    with pytest.raises(ValueError, match=accepted):
        DREAM("MetaBus-v0", execution_target_z="decoder")


def test_execution_buffer_links_each_episode_and_samples_whole_ones():
    # three envs interleave their transitions in the ring; the links still follow each episode
    env = make_vec_env("MetaBus-v0", n_envs=3, seed=0, env_kwargs={"variant": "map"})
    model = DREAM(env, seed=0, execution_sampling="episodes", **FAST)
    model.learn(900)
    buffer, n = model.replay_buffer.execution, len(model.replay_buffer.execution)
    links = buffer.next_in_episode[:n]
    linked = np.flatnonzero(links >= 0)
    assert len(linked) > n // 2  # most transitions have a successor (MetaBus executions last several steps)
    nxt = links[linked]
    assert (buffer.slots[nxt] == buffer.slots[linked]).all()
    assert (buffer.generations[nxt] == buffer.generations[linked]).all()
    assert (buffer.steps[nxt] == buffer.steps[linked] + 1).all()
    assert (buffer.dones[linked] == 0).all()  # nothing continues past a terminal transition
    np.testing.assert_array_equal(buffer.episode_links()[:n], links)  # what a saved buffer rebuilds

    exe, traj = model.replay_buffer.sample_execution(8, model._rng, episodes=model.execution_sampling == "episodes")
    owners = exe.trajectories.numpy()
    assert len(exe.slots) == len(traj.states) == 8 and sorted(set(owners)) == list(range(8))
    assert len(exe.actions) > 8  # whole episodes: more transitions than trajectories
    for k in range(8):
        steps = exe.steps.numpy()[owners == k]
        np.testing.assert_array_equal(steps, np.arange(len(steps)))  # from the episode's start, in order


def test_execution_buffer_pickled_before_the_links_rebuilds_them():
    model = DREAM("MetaBus-v0", seed=2, **FAST)
    model.learn(500)
    buffer = model.replay_buffer.execution
    state = dict(buffer.__dict__)
    del state["next_in_episode"], state["_last_index"]
    old = pickle.loads(pickle.dumps(buffer))
    old.__dict__.clear()
    old.__setstate__(state)
    np.testing.assert_array_equal(old.next_in_episode, buffer.next_in_episode)
    assert (old.next_in_episode >= 0).any()


def test_execution_reward_counts_group_the_replay_by_problem_and_instruction():
    from gymnasium import spaces

    from sb3_dream.dream.buffers import DreamReplayBuffer, ExecutionBuffer, ExplorationBuffer

    state_space = spaces.Box(0, 1, (2,), np.float32)
    obs_space = spaces.Dict({"obs": state_space, "instruction": spaces.MultiDiscrete([4])})
    exploration = ExplorationBuffer(2, 3, state_space, n_problem_features=1, device=th.device("cpu"))
    execution = ExecutionBuffer(20, obs_space, th.device("cpu"))
    buffer = DreamReplayBuffer(exploration, execution)

    def explore(problem):
        zeros = np.zeros(4)
        return exploration.add(np.zeros((4, 2)), np.zeros(3), zeros, zeros, 1, np.array([problem]))

    def execute(slot_generation, instruction, rewards):  # one execution episode, one env
        for step, reward in enumerate(rewards):
            execution.add(
                {
                    "states": np.zeros((1, 2)), "next_states": np.zeros((1, 2)),
                    "instructions": np.array([[instruction]]), "actions": np.array([0]),
                    "rewards": np.array([reward]), "dones": np.array([0.0]),
                    "slots": np.array([slot_generation[0]]), "generations": np.array([slot_generation[1]]),
                    "steps": np.array([step]),
                }
            )  # fmt: skip

    first, second = explore(problem=0), explore(problem=1)
    execute(first, 1, [0.0, 0.0, 1.0])
    execute(first, 1, [-1.0])
    execute(first, 2, [0.0, 0.5])
    execute(second, 1, [0.0, -1.0])
    counts = buffer.execution_reward_counts()
    np.testing.assert_array_equal(counts.problem_features, [[0], [0], [1]])
    np.testing.assert_array_equal(counts.instructions, [[1], [2], [1]])
    np.testing.assert_array_equal(counts.transitions, [4, 2, 2])
    np.testing.assert_array_equal(counts.episodes, [2, 1, 1])
    np.testing.assert_array_equal(counts.positive, [1, 1, 0])
    np.testing.assert_array_equal(counts.negative, [1, 0, 1])
    np.testing.assert_allclose(counts.reward_sum, [0.0, 0.5, -1.0])
    assert counts.unlinked == 0

    explore(problem=1)  # overwrites the first trajectory (capacity 2): its 6 transitions lose their problem
    counts = buffer.execution_reward_counts()
    assert counts.unlinked == 6
    np.testing.assert_array_equal(counts.problem_features, [[1]])
    np.testing.assert_array_equal(counts.transitions, [2])


def test_episode_batches_score_each_transition_as_the_paper_batch_does():
    # A batch of whole episodes (one trajectory per episode) gives the execution DDQN losses of the
    # same transitions sampled one by one (each with its own copy of its trajectory): the sharing
    # changes the cost, not the math. (The decoder and bottleneck losses weight trials, not
    # transitions, so they differ by design.)
    model = DREAM("MetaBus-v0", seed=4, encoder_variance=0.0, execution_sampling="episodes", **FAST)
    model.learn(500)
    exe, traj = model.replay_buffer.sample_execution(6, model._rng, episodes=model.execution_sampling == "episodes")
    owner = exe.trajectories.numpy()
    assert len(owner) > 6  # episodes of several transitions share their trajectory
    one_by_one = exe._replace(slots=exe.slots[owner], trajectories=th.arange(len(owner)))
    saved = {k: v.clone() for k, v in model.policy.state_dict().items()}
    optimizer = copy.deepcopy(model.policy.optimizer.state_dict())
    shared = updates.execution_update(model, exe, traj)
    model.policy.load_state_dict(saved)
    model.policy.optimizer.load_state_dict(optimizer)
    copied = updates.execution_update(model, one_by_one, model.replay_buffer.exploration.get(one_by_one.slots))
    for key in ("execution_loss_traj", "execution_loss_prob", "execution_q_mean"):
        assert shared[key] == pytest.approx(copied[key], rel=1e-5), key


def test_execution_sampling_is_saved_and_checked(tmp_path):
    model = DREAM("MetaBus-v0", seed=1, execution_sampling="episodes", **FAST)
    model.learn(1000)
    assert model._n_updates > 0
    model.save(tmp_path / "model.zip")
    assert DREAM.load(tmp_path / "model.zip").execution_sampling == "episodes"
    assert DREAM("MetaBus-v0").execution_sampling == "transitions"  # the paper's
    accepted = "execution_sampling='trials' is not valid; accepted values: 'transitions', 'episodes'"
    with pytest.raises(ValueError, match=accepted):
        DREAM("MetaBus-v0", execution_sampling="trials")


RECURRENT_EXECUTION = {
    "execution_sampling": "episodes",
    "policy_kwargs": {"execution_recurrent": True, "execution_hidden_sizes": (128, 128)},
}


@pytest.mark.parametrize(
    "target_z, networks",
    [(z, {}) for z in EXECUTION_TARGET_Z]
    + [(z, RECURRENT_EXECUTION) for z in EXECUTION_TARGET_Z]
    + [("own", {**RECURRENT_EXECUTION, "execution_z": "alternate"})],
    ids=[f"paper-{z}" for z in EXECUTION_TARGET_Z]
    + [f"recurrent-execution-{z}" for z in EXECUTION_TARGET_Z]
    + ["recurrent-execution-own-alternate"],
)
def test_parallel_updates_compute_what_sequential_updates_do(tmp_path, target_z, networks):
    # the worker thread runs the no-gradient passes (the target networks' Q^exe(s', z), the reward
    # codes) and the exploration update beside the execution update: same inputs, same order of
    # parameter changes
    kwargs = {**FAST, **networks}

    def trained(parallel: bool) -> DREAM:
        model = DREAM("MetaBus-v0", seed=3, parallel_updates=parallel, execution_target_z=target_z, **kwargs)
        model.learn(400)
        return model

    sequential, parallel = trained(False), trained(True)
    assert parallel._update_thread is not None and sequential._update_thread is None
    assert parallel._n_updates == sequential._n_updates > 0
    untrained = DREAM("MetaBus-v0", seed=3, **kwargs).policy.state_dict()
    for name, value in sequential.policy.state_dict().items():
        assert th.equal(value, parallel.policy.state_dict()[name]), name
    for net in ("exploration_q", "execution_q", "decoder"):  # both updates ran
        key = next(k for k in untrained if k.startswith(net + "."))
        assert not th.equal(untrained[key], parallel.policy.state_dict()[key]), key
    parallel.save(tmp_path / "parallel.zip")  # the thread is not saved; the option is
    assert DREAM.load(tmp_path / "parallel.zip").parallel_updates is True


def test_parallel_updates_auto_follows_the_cores(monkeypatch):
    import sb3_dream.dream.dream as dream_module

    model = DREAM("MetaBus-v0", seed=3, **FAST)
    assert model.parallel_updates == "auto"  # the default: resolved at each update, not saved resolved
    monkeypatch.setattr(dream_module, "available_cores", lambda: 1)
    assert model.updates_in_parallel is False
    model.learn(400)
    assert model._n_updates > 0 and model._update_thread is None  # one core: no second thread
    monkeypatch.setattr(dream_module, "available_cores", lambda: 2)
    assert model.updates_in_parallel is True
    model.learn(200, reset_num_timesteps=False)
    assert model._update_thread is not None
    model.parallel_updates = False  # an explicit choice wins over the cores
    assert model.updates_in_parallel is False
    for bad in (1, 0, "yes", None):  # 1 and 0 equal True and False but are not flags
        with pytest.raises(ValueError, match=r"parallel_updates=.*accepted values: True, False, 'auto'"):
            DREAM("MetaBandit-v0", parallel_updates=bad)


def test_execution_body_is_an_option(tmp_path):
    policy_kwargs = dict(execution_hidden_sizes=(128, 32))
    model = DREAM("MetaBandit-v0", policy_kwargs=policy_kwargs)
    assert policy_kwargs == dict(execution_hidden_sizes=(128, 32))  # the caller's dict is not changed
    widths = [m.out_features for m in model.policy.execution_q.body if isinstance(m, th.nn.Linear)]
    assert widths == [128, 32] and model.policy.execution_q.head.value.in_features == 32
    model.save(tmp_path / "wide.zip")
    loaded = DREAM.load(tmp_path / "wide.zip")
    assert loaded.policy.execution_hidden_sizes == (128, 32)
    default = DREAM("MetaBandit-v0").policy.execution_q.body
    assert [m.out_features for m in default if isinstance(m, th.nn.Linear)] == [64]  # the paper's
    for bad in [(), 128, (64, 0), ("64",)]:
        with pytest.raises(ValueError, match="execution_hidden_sizes"):
            DREAM("MetaBandit-v0", policy_kwargs=dict(execution_hidden_sizes=bad))


def test_execution_time_input_is_an_option_fed_the_step_within_each_execution_episode(tmp_path):
    starts = dict(exploration_learning_starts=5, execution_learning_starts=5)
    for n_envs in (1, 2):
        env = make_vec_env("MetaBus-v0", n_envs=n_envs, seed=0, env_kwargs={"n_exec_episodes": 2})
        model = DREAM(env, seed=0, policy_kwargs=dict(execution_time_input=True), **{**FAST, **starts})
        assert model.policy.execution_q.time_embed.num_embeddings == 20 + 1  # steps 0 .. horizon
        model.learn(400)
        assert model._n_updates > 0
        buf = model.replay_buffer.execution
        states, steps, dones = buf.states[: len(buf)], buf.steps[: len(buf)], buf.dones[: len(buf)]
        # Every execution episode starts at (4, 4) with step 0, two per trial.
        assert (states[steps == 0][:, :2] == [4, 4]).all() and 1 < steps.max() < 20
        assert int((steps == 0).sum()) >= 2 * model._episode_num
        if n_envs == 1:  # one env's rows in order: the step counts up and restarts after each end
            assert (steps[1:] == np.where(dones[:-1] == 1, 0, steps[:-1] + 1)).all()
    # The step changes Q: a greedy execution policy need not repeat itself on a second visit.
    q = model.policy.execution_q
    x = (th.tensor([[4, 5, 1]]), th.tensor([[1]]), th.zeros(1, 64))
    assert not th.allclose(q(*x, th.tensor([0]))[0], q(*x, th.tensor([3]))[0])
    with pytest.raises(ValueError, match="pass steps"):
        q(*x)
    with pytest.raises(ValueError, match="episode_start"):
        obs = {k: v for k, v in gym.make("MetaBus-v0").reset(seed=0)[0].items() if k != "episode_start"}
        model.predict(obs)
    model.save(tmp_path / "clock.zip")
    loaded = DREAM.load(tmp_path / "clock.zip")
    assert loaded.policy.execution_time_input and loaded.policy.execution_q.time_embed is not None
    assert DREAM("MetaBandit-v0").policy.execution_q.time_embed is None  # the paper's network
    with pytest.raises(ValueError, match="execution_time_input"):
        DREAM("MetaBandit-v0", policy_kwargs=dict(execution_time_input="yes"))
    env = gym.make("MetaBus-v0").unwrapped  # built by hand, the policy has no horizon for the clock
    with pytest.raises(ValueError, match="execution_time_input needs the inner-episode horizon"):
        DreamPolicy(
            env.observation_space, env.action_space, lambda _: 1e-4, env.problem_nvec, execution_time_input=True
        )


def test_recurrent_execution_q_learns_each_episode_as_acting_unrolled_it(tmp_path):
    # The update's fused pass over a batch of whole episodes gives every s and s' the LSTM output
    # that a step-by-step unroll from zeros at the episode's start gives.
    starts = dict(exploration_learning_starts=5, execution_learning_starts=5)
    env = make_vec_env("MetaBus-v0", n_envs=2, seed=0, env_kwargs={"n_exec_episodes": 2})
    model = DREAM(
        env,
        seed=0,
        execution_sampling="episodes",
        policy_kwargs=dict(execution_recurrent=True, execution_time_input=True),
        **{**FAST, **starts},
    )
    net = model.policy.execution_q
    assert net.recurrent and net.lstm.hidden_size == 64
    initial = {k: v.clone() for k, v in net.lstm.state_dict().items()}
    model.learn(600)
    assert model._n_updates > 0
    assert any(not th.equal(initial[k], v) for k, v in net.lstm.state_dict().items())  # it learns
    exe, _ = model.replay_buffer.sample_execution(8, model._rng, episodes=model.execution_sampling == "episodes")
    with th.no_grad():
        fused, fused_next = net._episode_inputs(exe)
        episodes, steps = exe.trajectories.numpy(), exe.steps.numpy()
        assert steps.max() > 2
        for e in range(8):
            rows = np.flatnonzero(episodes == e)[np.argsort(steps[episodes == e])]
            assert (steps[rows] == np.arange(len(rows))).all()  # the whole episode, from its start
            hidden, outs = None, []
            for j in rows:  # s_0 .. s_{L-1}, then the last transition's s'
                x = net.embed(exe.states[[j]], exe.instructions[[j]], exe.steps[[j]])
                out, hidden = net.recur(x[:, None], hidden)
                outs.append(out[0, 0])
            last = rows[-1:]
            s_next = net.embed(exe.next_states[last], exe.instructions[last], exe.steps[last] + 1)
            outs.append(net.recur(s_next[:, None], hidden)[0][0, 0])
            th.testing.assert_close(fused[rows], th.stack(outs[:-1]), rtol=1e-5, atol=1e-6)
            th.testing.assert_close(fused_next[rows], th.stack(outs[1:]), rtol=1e-5, atol=1e-6)

    # Acting: the LSTM state starts from zeros at each execution episode, carried step to step.
    trial_env = gym.make("MetaBus-v0", n_exec_episodes=2)
    obs, _ = trial_env.reset(seed=3)
    state, start, unrolled, done = None, True, None, False
    while not done:
        action, state = model.predict(obs, state, np.array([start]), deterministic=True)
        if obs["phase"] == 1:
            with th.no_grad():
                x = net.embed(*(th.as_tensor(obs[k])[None] for k in ("obs", "instruction")), th.as_tensor(state[9]))
                unrolled = net.recur(x[:, None], None if obs["episode_start"] else unrolled)[1]
            np.testing.assert_allclose(state[-2], unrolled[0].numpy(), rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(state[-1], unrolled[1].numpy(), rtol=1e-5, atol=1e-6)
        obs, _, terminated, truncated, _ = trial_env.step(action)
        start, done = False, terminated or truncated
    assert unrolled is not None

    model.save(tmp_path / "recurrent.zip")
    loaded = DREAM.load(tmp_path / "recurrent.zip")
    assert loaded.policy.execution_recurrent and loaded.policy.execution_q.recurrent
    assert not DREAM("MetaBandit-v0").policy.execution_q.recurrent  # the paper's feed-forward network
    with pytest.raises(ValueError, match="execution_recurrent=True needs execution_sampling='episodes'"):
        DREAM("MetaBus-v0", policy_kwargs=dict(execution_recurrent=True))
    with pytest.raises(ValueError, match="execution_recurrent must be True or False, got 'yes'"):
        DREAM("MetaBus-v0", execution_sampling="episodes", policy_kwargs=dict(execution_recurrent="yes"))


def test_execution_instruction_mlp_off_makes_the_first_layer_additive_in_the_recipe_parts(tmp_path):
    state, z = th.tensor([[1, 1, 3, 0, 0, 0]]), th.randn(1, 64)

    def additive(q):  # the body's first pre-activation, before any ReLU mixes the parts
        first = lambda recipe: q.body[0](th.cat([q.embed(state, th.tensor([recipe])), z], dim=-1))  # noqa: E731
        # (3, 6) is a held-out recipe; (3, 1) and (7, 6) are training ones sharing a part with it.
        return th.allclose(first([3, 6]), first([3, 1]) + first([7, 6]) - first([7, 1]), atol=1e-5)

    model = DREAM("MetaCook-v0", seed=0, policy_kwargs=dict(execution_instruction_mlp=False))
    assert additive(model.policy.execution_q)
    assert not additive(DREAM("MetaCook-v0", seed=0).policy.execution_q)  # the paper's MLP mixes them
    model.save(tmp_path / "parts.zip")
    loaded = DREAM.load(tmp_path / "parts.zip")
    assert loaded.policy.execution_instruction_mlp is False and additive(loaded.policy.execution_q)
    with pytest.raises(ValueError, match="execution_instruction_mlp"):
        DREAM("MetaBandit-v0", policy_kwargs=dict(execution_instruction_mlp=0))


def test_execution_weight_decay_shrinks_the_execution_q_network_alone(tmp_path):
    def step_on_zero_gradients(policy, nets):  # Adam's step is then 0: only the decay moves a weight
        before = [[p.detach().clone() for p in net.parameters()] for net in nets]
        for p in policy.parameters():
            p.grad = th.zeros_like(p)
        policy.optimizer.step()
        return [list(zip(b, net.parameters())) for b, net in zip(before, nets)]

    def shrunk(pairs):  # each weight times (1 - lr * decay), lr 1e-3, decay 0.5
        return all(th.allclose(p.detach(), b * (1 - 1e-3 * 0.5)) for b, p in pairs)

    model = DREAM("MetaCook-v0", seed=0, learning_rate=1e-3, policy_kwargs=dict(execution_weight_decay=0.5))
    policy = model.policy
    execution_q, encoder, decoder = step_on_zero_gradients(policy, (policy.execution_q, policy.encoder, policy.decoder))
    assert shrunk(execution_q)
    assert all(th.equal(p.detach(), b) for b, p in encoder + decoder)
    model.save(tmp_path / "decay.zip")
    loaded = DREAM.load(tmp_path / "decay.zip").policy
    assert loaded.execution_weight_decay == 0.5
    assert shrunk(step_on_zero_gradients(loaded, (loaded.execution_q,))[0])
    paper = DREAM("MetaCook-v0", seed=0).policy  # the paper's Adam by default: no decay anywhere
    assert all(th.equal(p.detach(), b) for b, p in step_on_zero_gradients(paper, (paper.execution_q,))[0])
    for bad in (-0.1, "0.1", True, float("inf")):
        with pytest.raises(ValueError, match="execution_weight_decay must be a number >= 0"):
            DREAM("MetaBandit-v0", policy_kwargs=dict(execution_weight_decay=bad))
    with pytest.raises(ValueError, match="execution_weight_decay needs the default optimizer"):
        DREAM("MetaBandit-v0", policy_kwargs=dict(execution_weight_decay=0.1, optimizer_kwargs=dict(weight_decay=1)))


def test_exploration_time_input_is_an_option_fed_the_step_within_the_exploration_episode(tmp_path):
    starts = dict(exploration_learning_starts=5, execution_learning_starts=5)
    env = make_vec_env("MetaBus-v0", n_envs=2, seed=0)
    model = DREAM(env, seed=0, policy_kwargs=dict(exploration_time_input=True), **{**FAST, **starts})
    q = model.policy.exploration_q
    assert q.time_embed.num_embeddings == 20 + 1 and model.policy.execution_q.time_embed is None
    seen = []  # the steps each call of the online exploration Q gets
    q.register_forward_hook(lambda module, args, out: seen.append(args[4].cpu().numpy().copy()))
    model.learn(400)
    assert model._n_updates > 0
    training = [s for s in seen if s.shape[1] > 1]
    # training: each trajectory's states are steps 0 .. T
    assert training and all((s == np.arange(s.shape[1])).all() for s in training)
    # acting: the step of the current state, through a whole trial played with predict
    seen.clear()
    trial_env = gym.make("MetaBus-v0")
    obs, state, n_explored = trial_env.reset(seed=1)[0], None, 0
    while True:
        n_explored += int(obs["phase"]) == 0
        action, state = model.predict(obs, state, episode_start=np.array([obs["episode_start"]]))
        obs, _, terminated, truncated, _ = trial_env.step(action)
        if terminated or truncated:
            break
    assert n_explored >= 1 and [int(s[0, 0]) for s in seen] == list(range(n_explored))
    # The step changes Q.
    x = (th.tensor([[[4, 4, 0]]]), th.tensor([[0]]), th.zeros(1, 1, 1))
    assert not th.allclose(q(*x, None, th.tensor([[0]]))[0], q(*x, None, th.tensor([[7]]))[0])
    with pytest.raises(ValueError, match="pass steps"):
        q(*x)
    model.save(tmp_path / "clock.zip")
    loaded = DREAM.load(tmp_path / "clock.zip")
    assert loaded.policy.exploration_time_input and loaded.policy.exploration_q.time_embed is not None
    assert DREAM("MetaBandit-v0").policy.exploration_q.time_embed is None  # the paper's network
    with pytest.raises(ValueError, match="exploration_time_input"):
        DREAM("MetaBandit-v0", policy_kwargs=dict(exploration_time_input=1))


def test_execution_buffers_saved_before_the_step_was_stored_load_with_step_zero():
    from sb3_dream.dream.buffers import DreamReplayBuffer

    model = DREAM("MetaBus-v0", seed=0, **FAST)
    model.learn(100)
    buf = model.replay_buffer.execution
    saved = {k: v for k, v in buf.__dict__.items() if k != "steps"}  # what such a pickle holds
    restored = type(buf).__new__(type(buf))
    restored.__setstate__(saved)  # as pickle.load does
    assert restored.steps.shape == buf.actions.shape and not restored.steps.any()
    replay = DreamReplayBuffer(model.replay_buffer.exploration, restored)
    assert replay.sample_transitions(4, np.random.default_rng(0)).steps.tolist() == [0] * 4


def test_bad_input():
    with pytest.raises(TypeError, match="Dict observation"):
        DREAM("CartPole-v1")
    with pytest.raises(ValueError, match="batch_size"):
        DREAM("MetaBandit-v0", batch_size=0)
    with pytest.raises(ValueError, match="env is required"):
        DREAM("DreamPolicy")
    # each real-valued hyperparameter is named alone, whichever is wrong
    for name in ("encoder_variance", "bottleneck_threshold", "bottleneck_weight", "max_grad_norm"):
        with pytest.raises(ValueError, match=f"^{name} must be a number >= 0, got -1.0$"):
            DREAM("MetaBandit-v0", **{name: -1.0})
    with pytest.raises(ValueError, match=r"^encoder_variance must be a number >= 0, got nan$"):
        DREAM("MetaBandit-v0", encoder_variance=float("nan"))
    with pytest.raises(ValueError, match=r"^bottleneck_threshold must be a number >= 0, got '10'$"):
        DREAM("MetaBandit-v0", bottleneck_threshold="10")


@pytest.mark.slow
@pytest.mark.parametrize(
    "options",
    [{}, dict(execution_sampling="episodes", policy_kwargs=dict(execution_recurrent=True))],
    ids=["paper", "recurrent-execution"],
)
def test_dream_learns_the_bandit_that_needs_exploration(options):
    """MetaBandit |A| = 8: only the informative action reveals which of 8 actions pays (chance 1/8)."""
    model = DREAM(
        "MetaBandit-v0",
        seed=0,
        exploration_learning_starts=50,
        execution_learning_starts=50,
        eps_decay_steps=4000,
        target_update_interval=200,
        **options,
    )
    model.learn(8000)
    result = evaluate_meta(model, "MetaBandit-v0", n_trials=100)
    assert result.mean >= 0.9


def test_f_variance_by_feature_splits_an_additive_code_between_its_parts():
    from sb3_dream.dream import f_variance_by_feature

    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(3, 4)), rng.normal(size=(5, 4))  # the code of each part's values
    features = np.array([(i, j, 0) for i in range(3) for j in range(5)])  # a product; column 2 constant
    f = a[features[:, 0]] + b[features[:, 1]] + 7.0
    explained = f_variance_by_feature(f, features)
    var = lambda x: float(((x - x.mean(0)) ** 2).sum(1).mean())  # noqa: E731
    assert explained == pytest.approx([var(a), var(b), 0.0])
    assert sum(explained) == pytest.approx(var(f))  # additive parts of a product add up
    # a code that ignores a part leaves it nothing
    assert f_variance_by_feature(a[features[:, 0]], features)[1] == pytest.approx(0.0, abs=1e-12)


def test_diagnose_side_by_side_is_diagnose_one_trial_at_a_time(bus_model):
    """The privileged agents number the trials as the side-by-side runner starts them: the same
    code f(T) per trial, so every number matches (z = g, f(T), noisy f(T), the oracle's exploration)."""
    from sb3_dream.dream import diagnose

    ids = [3, 40, 3, 100, 7]
    one = diagnose(bus_model, "MetaBus-v0", n_trials=7, seed=7, problem_ids=ids, n_envs=1)
    side = diagnose(bus_model, "MetaBus-v0", n_trials=7, seed=7, problem_ids=ids, n_envs=3)
    assert one.return_f_noisy is not None and one.return_g_optimal_exploration is not None
    for key, value in one.as_dict().items():
        assert side.as_dict()[key] == pytest.approx(value, rel=1e-5, abs=1e-6), key
    with pytest.raises(ValueError, match="n_envs"):
        diagnose(bus_model, "MetaBus-v0", n_trials=2, n_envs=0)
    from dream_envs import make_oracle
    from sb3_dream.dream import PrivilegedBatchAgent

    with pytest.raises(ValueError, match="explorers has 1 agents for 3 slots: pass one per slot"):
        PrivilegedBatchAgent(bus_model, ids, "g", explorers=[make_oracle(gym.make("MetaBus-v0"))]).reset(3)


def test_exhaustive_diagnose_plays_and_weights_the_pairs_evaluate_meta_does(bus_model):
    """diagnose(exhaustive=True) pins the split's (problem, goal) pairs as evaluate_meta does: its
    z = g return is the model's exhaustive meta-test return, and its privileged agents read the
    code of each pinned problem (z = f(T) played by hand on those pairs gives the same)."""
    from sb3_dream.dream import PrivilegedBatchAgent, diagnose, exploration_gains
    from sb3_dream.evaluation import exhaustive_cases

    env = gym.make("MetaBus-v0", split="train")
    d = diagnose(bus_model, "MetaBus-v0", n_trials=1, split="train", exhaustive=True)
    meta_test = evaluate_meta(bus_model, "MetaBus-v0", n_trials=1, split="train", exhaustive=True)
    assert d.n_trials == meta_test.n_trials == 212  # 53 training problems x 4 goals
    assert d.return_g == pytest.approx(meta_test.mean, abs=1e-9)
    assert d.exploration_length == pytest.approx(meta_test.mean_exploration_length, abs=1e-9)
    pids, instructions, _ = exhaustive_cases(env, "train", 1)
    by_hand = PrivilegedBatchAgent(bus_model, pids, "f")
    weighted = evaluate_meta(by_hand, "MetaBus-v0", 1, "train", exhaustive=True)
    assert d.return_f == pytest.approx(weighted.mean, abs=1e-9)
    gains = exploration_gains(bus_model, "MetaBus-v0", n_trials=1, split="train", exhaustive=True)
    assert gains.problem_ids.tolist() == pids.tolist()
    with pytest.raises(ValueError, match="problem_ids and exhaustive"):
        diagnose(bus_model, "MetaBus-v0", problem_ids=[0], exhaustive=True)


def test_exploration_gains_reward_each_step_as_training_relabels_it(bus_model, monkeypatch):
    from dream_envs import play_trials
    from sb3_dream.dream import exploration_gains

    ids = [3, 40, 3, 100, 7, 40]
    c = bus_model.reward_penalty

    def check_by_hand(gains) -> None:
        """Equation 5 on each trajectory alone (the function pads them into one batch)."""
        assert gains.problem_ids.tolist() == ids and gains.reward_penalty == c == 0.01
        f = bus_model.encode(np.array(ids), noisy=False)
        for k, ((states, actions), rewards) in enumerate(zip(gains.trajectories, gains.rewards)):
            assert len(states) == len(actions) + 1 == len(rewards) + 1
            with th.no_grad():
                g = bus_model.policy.decoder(th.as_tensor(states[None]), th.as_tensor(actions[None]))[0].numpy()
            d = ((f[k] - g) ** 2).sum(axis=1)
            assert rewards == pytest.approx(d[:-1] - d[1:] - c, rel=1e-4, abs=1e-5)
            assert gains.information_gain()[k] == pytest.approx(d[0] - d[-1], rel=1e-4, abs=1e-5)
        by_step = gains.by_step()
        assert len(by_step) == max(map(len, gains.rewards))
        for t, mean in enumerate(by_step):  # over the trials that took step t
            assert mean == pytest.approx(np.mean([r[t] for r in gains.rewards if len(r) > t]))

    greedy = exploration_gains(bus_model, "MetaBus-v0", n_trials=6, seed=7, problem_ids=ids, n_envs=2)
    check_by_hand(greedy)
    # the trajectories are the greedy meta-test explorations of these trials
    test_env = gym.make("MetaBus-v0", split="test")
    played = list(play_trials(test_env, as_trial_agent(bus_model), 6, seed=7, problem_ids=ids))
    assert [a.tolist() for _, a in greedy.trajectories] == [t["exploration_actions"] for t in played]
    # diagnose() rewards its own z = g trials: the same trials, the same rewards, played once
    from sb3_dream.dream import diagnose

    diagnosed = diagnose(bus_model, "MetaBus-v0", n_trials=6, seed=7, problem_ids=ids, n_envs=2).exploration_gains
    check_by_hand(diagnosed)
    assert [a.tolist() for _, a in diagnosed.trajectories] == [t["exploration_actions"] for t in played]
    for ours, theirs in zip(diagnosed.rewards, greedy.rewards):
        assert ours == pytest.approx(theirs, rel=1e-5, abs=1e-6)
    # With a scripted explorer its explorations are rewarded instead (here the env's oracle).
    from dream_envs import make_oracle

    guided = exploration_gains(bus_model, "MetaBus-v0", 6, seed=7, problem_ids=ids, n_envs=2, explorer=make_oracle)
    check_by_hand(guided)
    oracle_played = play_trials(test_env, make_oracle(test_env), 6, seed=7, problem_ids=ids)
    assert [a.tolist() for _, a in guided.trajectories] == [t["exploration_actions"] for t in oracle_played]
    # Random actions end the explorations at different steps: the padded batch still gives each its own.
    rng = np.random.default_rng(0)
    monkeypatch.setattr(
        "sb3_dream.dream.acting.epsilon_greedy", lambda greedy, eps, n, _: rng.integers(n, size=len(greedy))
    )
    random = exploration_gains(bus_model, "MetaBus-v0", n_trials=6, seed=7, problem_ids=ids, n_envs=3)
    assert len({len(r) for r in random.rewards}) > 1
    check_by_hand(random)
    with pytest.raises(TypeError, match="model"):
        exploration_gains("not a model", "MetaBus-v0")


def test_diagnose_compares_meta_test_with_the_privileged_execution_policy(bus_model, monkeypatch):
    from sb3_dream.dream import diagnose

    ids = [3, 40, 3, 100]
    d = diagnose(bus_model, "MetaBus-v0", n_trials=4, seed=7, problem_ids=ids)
    # return_g is the ordinary meta-test of these trials
    assert d.return_g == pytest.approx(evaluate_meta(bus_model, "MetaBus-v0", n_trials=4, seed=7, problem_ids=ids).mean)
    assert d.decoder_error > 0 and d.n_trials == 4 and 1 <= d.exploration_length <= 20
    split_ids = gym.make("MetaBus-v0", split="test").unwrapped.problem_ids("test")
    f = bus_model.encode(split_ids, noisy=False)
    brute = ((f[:, None] - f[None]) ** 2).sum(-1)
    assert d.f_spread == pytest.approx(brute.sum() / (len(f) * (len(f) - 1)), rel=1e-4)
    f_ids = bus_model.encode(np.array(ids), noisy=False)
    assert d.f_norm_sq == pytest.approx(float((f_ids**2).sum(1).mean()), rel=1e-5)
    # one entry per problem feature (colored permutation, four gray buses), each the variance of
    # the mean code of the problems that share the feature's value
    features = gym.make("MetaBus-v0").unwrapped.problem_feature_table()[split_ids]
    assert len(d.f_variance_by_feature) == 5
    for k, explained in enumerate(d.f_variance_by_feature):
        means = {v: f[features[:, k] == v].mean(0) for v in np.unique(features[:, k])}
        by_problem = np.stack([means[v] for v in features[:, k]]) - f.mean(0)
        assert explained == pytest.approx(float((by_problem**2).sum(1).mean()), rel=1e-4)

    # The privileged agent is public, for reports: on the same trials it scores diagnose's return_f.
    from sb3_dream.dream import PrivilegedAgent, trial_problem_ids

    privileged = PrivilegedAgent(bus_model, ids, "f")
    # the trials diagnose plays
    assert trial_problem_ids(split_ids, 6, seed=7, problem_ids=ids).tolist() == ids + ids[:2]
    drawn = np.random.default_rng(7).choice(split_ids, size=4)
    assert trial_problem_ids(split_ids, 4, seed=7).tolist() == drawn.tolist()
    with pytest.raises(ValueError, match="problem_ids must not be empty"):
        trial_problem_ids(split_ids, 4, problem_ids=[])
    assert evaluate_meta(privileged, "MetaBus-v0", n_trials=4, seed=7, problem_ids=ids).mean == d.return_f
    with pytest.raises(ValueError, match="z_source='h' is not valid; accepted values: 'g', 'f', 'f_noisy'"):
        PrivilegedAgent(bus_model, ids, "h")

    # With the env's oracle as the explorer: the env sees the oracle's exploration actions, the
    # decoder reads that trajectory (its z is g of it), and execution is the model's.
    from dream_envs import make_oracle
    from dream_envs import play_trials

    env = gym.make("MetaBus-v0", split="test")
    guided = PrivilegedAgent(bus_model, ids, "g", explorer=make_oracle(env))
    trials = list(play_trials(env, guided, 2, seed=7, problem_ids=ids))
    oracle_trials = list(play_trials(env, make_oracle(env), 2, seed=7, problem_ids=ids))
    assert [t["exploration_actions"] for t in trials] == [t["exploration_actions"] for t in oracle_trials]
    actions = trials[1]["exploration_actions"]
    assert guided.state.actions[0, : len(actions)].tolist() == actions  # what the decoder read
    assert d.return_g_optimal_exploration is not None and d.decoder_error_optimal_exploration > 0
    assert "with z = g of the optimal exploration" in d.returns_text()

    # A perfect decoder (g = f of the trial's problem): both runs act on the same z.
    def perfect_decoder(policy, state, idx, n):
        return bus_model.encode(np.full(len(idx), 40), noisy=False)

    monkeypatch.setattr("sb3_dream.dream.acting.decode", perfect_decoder)
    perfect = diagnose(bus_model, "MetaBus-v0", n_trials=3, seed=7, problem_ids=[40])
    assert perfect.decoder_error == pytest.approx(0.0, abs=1e-8)
    assert perfect.return_g == perfect.return_f
    # ... and so does the decoder of the optimal exploration: the three runs act alike
    assert perfect.decoder_error_optimal_exploration == pytest.approx(0.0, abs=1e-8)
    assert perfect.return_g_optimal_exploration == perfect.return_f
    # The noisy code's run draws its noise from the seed; with a vanishing rho^2 it is f(T)'s run.
    assert d.return_f_noisy is not None
    monkeypatch.setattr(bus_model, "encoder_variance", 1e-12)
    tiny = diagnose(bus_model, "MetaBus-v0", n_trials=3, seed=7, problem_ids=[40])
    assert tiny.return_f_noisy == tiny.return_f
    monkeypatch.setattr(bus_model, "bottleneck", False)  # DREAM (no bottleneck): no noise, no third run
    assert diagnose(bus_model, "MetaBus-v0", n_trials=3, seed=7, problem_ids=[40]).return_f_noisy is None
    with pytest.raises(TypeError, match="model"):
        diagnose("not a model", "MetaBus-v0")


def test_sb3_argument_names_keep_sb3s_meaning():
    starts = {**FAST, "exploration_learning_starts": 1, "execution_learning_starts": 1}
    model = DREAM("MetaBus-v0", seed=0, learning_starts=300, **starts)
    model.learn(280)
    assert model._n_updates == 0  # no update before learning_starts env steps
    model.learn(200, reset_num_timesteps=False)
    assert model._n_updates > 0
    # gradient_steps updates of each part per train_freq env steps, whatever the number of envs
    counts = []
    for n_envs, gradient_steps in [(1, 1), (1, 2), (2, 1)]:
        env = make_vec_env("MetaBus-v0", n_envs=n_envs, seed=0)
        model = DREAM(env, seed=0, gradient_steps=gradient_steps, **starts)
        model.learn(400)
        counts.append(model._n_updates)
    assert counts[1] == 2 * counts[0] and abs(counts[2] - counts[0]) <= 1 and counts[0] > 50
    assert DREAM("MetaBus-v0", train_freq=(8, "step")).train_every == 8
    with pytest.raises(ValueError, match="train_freq"):
        DREAM("MetaBus-v0", train_freq=(1, "episode"))
    for name, value, equivalent in [
        ("exploration_fraction", 0.1, "eps_decay_steps"),
        ("replay_buffer_class", None, "execution_buffer_size"),
        ("action_noise", None, "epsilon-greedy"),
    ]:
        with pytest.raises(ValueError, match=f"SB3's '{name}'.*{equivalent}"):
            DREAM("MetaBus-v0", **{name: value})
    with pytest.raises(TypeError, match="learnin_starts"):
        DREAM("MetaBus-v0", learnin_starts=100)
    with pytest.raises(ValueError, match="learning_starts"):
        DREAM("MetaBus-v0", learning_starts=-1)
    with pytest.raises(ValueError, match="pass z_dim=8 to DREAM"):
        DREAM("MetaBus-v0", policy_kwargs=dict(z_dim=8))


def test_tau_is_sb3s_polyak_coefficient_for_every_target(tmp_path):
    model = DREAM("MetaBus-v0", seed=0, **{**FAST, "tau": 0.25, "target_update_interval": 1})
    policy = model.policy
    with th.no_grad():
        for net in policy.onlines():
            for param in net.parameters():
                param.add_(1.0)
    targets = [[t.clone() for t in target.parameters()] for target in policy.targets()]
    policy.sync_targets(model.tau)  # each target moves a quarter of the way to its online network
    for online, target, old in zip(policy.onlines(), policy.targets(), targets):
        for o, t, t_old in zip(online.parameters(), target.parameters(), old):
            th.testing.assert_close(t, 0.75 * t_old + 0.25 * o)
    model.learn(400)
    assert model._n_updates > 0
    model.save(tmp_path / "soft.zip")
    assert DREAM.load(tmp_path / "soft.zip").tau == 0.25
    assert DREAM.load(tmp_path / "soft.zip", tau=0.5).tau == 0.5
    assert DREAM("MetaBus-v0").tau == 1.0  # the paper's hard copies by default
    with pytest.raises(ValueError, match="tau must be in \\[0, 1\\] \\(1: hard target updates\\), got 1.5"):
        DREAM("MetaBus-v0", tau=1.5)
    with pytest.raises(ValueError, match="tau must be a number >= 0, got -0.9"):
        DREAM.load(tmp_path / "soft.zip", tau=-0.9)


def test_saves_from_before_tau_load_with_hard_target_updates():
    # DREAM's saves before it took SB3's tau hold SB3's unused default 0.005 under "tau"
    path = pathlib.Path(__file__).resolve().parents[1] / "models" / "dream_metabus_map.zip"
    with zipfile.ZipFile(path) as archive:
        assert json.loads(archive.read("data"))["tau"] == 0.005
    assert DREAM.load(path).tau == 1.0


@pytest.mark.parametrize("parallel", [False, True])
def test_execution_update_ratio_makes_k_execution_steps_per_exploration_step(tmp_path, parallel):
    model = DREAM("MetaBus-v0", seed=0, execution_update_ratio=3, parallel_updates=parallel, **FAST)
    model.learn(400)
    policy = model.policy

    def steps(optimizer, net):  # Adam's step count of one of the network's parameters
        return int(optimizer.state[next(net.parameters())]["step"])

    before = steps(policy.exploration_optimizer, policy.exploration_q), steps(policy.optimizer, policy.execution_q)
    n_updates = model._n_updates
    model.train(gradient_steps=2, batch_size=8)
    after = steps(policy.exploration_optimizer, policy.exploration_q), steps(policy.optimizer, policy.execution_q)
    assert (after[0] - before[0], after[1] - before[1]) == (2, 6)
    assert model._n_updates == n_updates + 2  # target syncs keep counting exploration updates
    model.save(tmp_path / "ratio.zip")
    assert DREAM.load(tmp_path / "ratio.zip").execution_update_ratio == 3


def test_execution_update_ratio_defaults_to_algorithm_1_and_is_checked():
    assert DREAM("MetaBus-v0").execution_update_ratio == 1
    path = pathlib.Path(__file__).resolve().parents[1] / "models" / "dream_metabus_map.zip"
    assert DREAM.load(path).execution_update_ratio == 1  # saved before the option existed
    for value in (0, 1.5, True):
        with pytest.raises(ValueError, match=f"execution_update_ratio must be an integer >= 1, got {value!r}"):
            DREAM("MetaBus-v0", execution_update_ratio=value)


@pytest.mark.parametrize(
    "options", [{}, {**RECURRENT_EXECUTION, "execution_n_step": 3}], ids=["paper", "recurrent-episodes-3-step"]
)
def test_execution_z_alternate_computes_one_of_algorithm_1s_two_losses(options):
    # one update with one z source gives that source's DDQN loss of the two-source update on the
    # same batch (the same draw of F's noise), and the same decoder and bottleneck losses
    model = DREAM("MetaBus-v0", seed=0, parallel_updates=False, **FAST, **options)
    model.learn(400)
    exe, traj = model._sample_execution(8)
    saved = {k: v.clone() for k, v in model.policy.state_dict().items()}
    optimizer = copy.deepcopy(model.policy.optimizer.state_dict())

    def update(sources):
        model.policy.load_state_dict(saved)
        model.policy.optimizer.load_state_dict(optimizer)
        th.manual_seed(5)
        return updates.execution_update(model, exe, traj, sources=sources)

    both, decoder, encoder = update(updates.Z_SOURCES), update(("decoder",)), update(("encoder",))
    assert set(both) - set(decoder) == {"execution_loss_prob"} and set(both) - set(encoder) == {"execution_loss_traj"}
    assert decoder["execution_loss_traj"] == pytest.approx(both["execution_loss_traj"], rel=1e-5)
    assert encoder["execution_loss_prob"] == pytest.approx(both["execution_loss_prob"], rel=1e-5)
    assert both["execution_loss_traj"] != pytest.approx(both["execution_loss_prob"], rel=1e-3)  # two different losses
    for key in ("decoder_loss", "bottleneck_loss", "f_norm_sq"):
        assert decoder[key] == encoder[key] == both[key], key


def test_execution_z_alternate_takes_the_sources_in_turn_and_is_saved(tmp_path):
    model = DREAM("MetaBus-v0", seed=0, execution_z="alternate", execution_update_ratio=2, **FAST)
    model.learn(400)
    turn = model._n_execution_updates
    assert turn > 0
    losses = [key for stats in model._update(8, True, True) for key in stats if key.startswith("execution_loss")]
    expected = ["execution_loss_traj", "execution_loss_prob"]
    assert losses == (expected if turn % 2 == 0 else expected[::-1])  # both of the ratio's updates, in turn
    assert model._n_execution_updates == turn + 2
    model.save(tmp_path / "alternate.zip")
    loaded = DREAM.load(tmp_path / "alternate.zip")
    assert (loaded.execution_z, loaded._n_execution_updates) == ("alternate", turn + 2)


def test_execution_z_defaults_to_algorithm_1_and_is_checked():
    assert DREAM("MetaBus-v0").execution_z == "both"
    path = pathlib.Path(__file__).resolve().parents[1] / "models" / "dream_metabus_map.zip"
    assert DREAM.load(path).execution_z == "both"  # saved before the option existed
    with pytest.raises(ValueError, match=r"execution_z=.*accepted values: 'both', 'alternate'"):
        DREAM("MetaBus-v0", execution_z="encoder")


def test_predict_without_state_in_execution_warns_once(bus_model):
    import warnings

    env = gym.make("MetaBus-v0")
    obs, _ = env.reset(seed=0)
    bus_model.predict(obs)  # an exploration step starts the trial: nothing is lost, no warning
    while obs["phase"] == 0:
        obs, *_ = env.step(0)
    try:
        with pytest.warns(UserWarning, match="without state"):
            bus_model.predict(obs)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            bus_model.predict(obs)  # once only
            bus_model.predict(obs, state=bus_model.new_trial_state(1).as_tuple())  # with a state: never
    finally:
        bus_model._warned_stateless_predict = False
