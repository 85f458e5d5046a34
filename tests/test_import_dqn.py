"""IMPORT: recurrent dueling double DQN whose z alternates per trial between e(T) and e(tau_:t)."""

import inspect

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.env_util import make_vec_env

from conftest import _RecordActions
from sb3_dream import IMPORT, RL2DQN
from sb3_dream.common.buffers import SequenceReplayBuffer
from sb3_dream.common.wrappers import RL2ObservationWrapper
from sb3_dream.evaluation import evaluate_meta
from sb3_dream.import_dqn import ProblemSequenceSamples, diagnose, import_aux_loss
from test_rl2dqn import SMALL_NET, CueMemoryEnv


def small_model(env, **kwargs):
    params = dict(learning_starts=20, buffer_size=200, batch_size=4, train_freq=1, seed=0, policy_kwargs=SMALL_NET)
    params.update(kwargs)
    return IMPORT(params.pop("policy", "MultiInputLstmPolicy"), env, **params)


class _ScrambleProblemId(gym.Wrapper):
    """Replaces ``info["problem_id"]`` by a random ID: a model that reads it acts differently."""

    def _scramble(self, info):
        return {**info, "problem_id": int(np.random.randint(1000))}

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return obs, self._scramble(info)

    def step(self, action):
        *out, info = self.env.step(action)
        return (*out, self._scramble(info))


class _LogProblems(gym.Wrapper):
    """Records the problem of each trial the env starts."""

    def __init__(self, env):
        super().__init__(env)
        self.problems = []

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.problems.append(info["problem_id"])
        return obs, info


# ---------------------------------------------------------------------- construction
def test_paper_defaults_sizes_and_short_form():
    model = IMPORT("MetaBus-v0")
    assert isinstance(model.policy, IMPORT.policy_aliases["MultiInputLstmPolicy"])
    # the hyperparameters are RL2DQN's (the paper's Table 1), argument for argument
    rl2 = inspect.signature(RL2DQN.__init__).parameters
    mine = inspect.signature(IMPORT.__init__).parameters
    assert set(rl2) < set(mine) and set(mine) - set(rl2) == {"aux_loss_coef"}
    assert all(mine[k].default == p.default for k, p in rl2.items() if k != "policy_kwargs")
    assert (model.learning_rate, model.batch_size, model.buffer_size, model.sequence_length) == (1e-4, 32, 16_000, 50)
    assert (model.target_update_interval, model.train_every, model.learning_starts, model.max_grad_norm) == (
        5000, 4, 16_000, 10.0)  # fmt: skip
    assert model.exploration_schedule(500_000) == pytest.approx(0.01) and model.aux_loss_coef == 1.0
    net = model.q_net
    assert (net.lstm.input_size, net.lstm.hidden_size) == (64, 64)  # RL²'s history encoder
    cur = net.current_embedder.embedders
    assert set(cur) == {"obs", "instruction"} and cur["obs"].embed_dim == cur["instruction"].embed_dim == 64
    assert net.q_hidden[0].in_features == 64 + 64 + 64 and net.q_hidden[0].out_features == 64
    assert net.head.value.in_features == 64 and net.head.advantage.out_features == 9
    pe = net.problem_embedder
    assert pe.embedding.embedding_dim == 32 and [m.out_features for m in pe.mlp if isinstance(m, th.nn.Linear)] == [
        256, 64]  # fmt: skip
    assert model.policy.q_net is net and len(model.problem_table) == model.trial_spec["n_problems"]
    n_opt = sum(p.numel() for g in model.policy.optimizer.param_groups for p in g["params"])
    assert n_opt == sum(p.numel() for p in net.parameters())


def keys_without_gradient(model, batch) -> list:
    """The policy's state_dict keys, target networks aside, that one loss backward leaves without a
    gradient: parameters the model saves but never trains. (A gradient may be zero where the batch
    holds no signal, e.g. no reward yet; it is None only for what the loss never reads.)"""
    model.policy.optimizer.zero_grad(set_to_none=True)
    loss, _ = model._loss(batch)
    loss.backward()
    params = dict(model.policy.named_parameters())
    return [
        key
        for key in model.policy.state_dict()
        if not key.startswith("q_net_target.") and (key not in params or params[key].grad is None)
    ]


def layers_built_and_dropped(monkeypatch, build) -> list:
    """The ``nn.Linear`` layers that ``build()`` (a model) constructs but its policy does not keep
    outside the target network (a deep copy, built without constructing layers): each drew its
    initial weights for nothing."""
    built = []
    init = th.nn.Linear.__init__

    def recording_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        built.append(self)

    monkeypatch.setattr(th.nn.Linear, "__init__", recording_init)
    policy = build().policy
    target = {id(m) for m in policy.q_net_target.modules()}
    kept = {id(m) for m in policy.modules() if id(m) not in target}
    return [m for m in built if id(m) not in kept]


def test_the_network_builds_only_what_its_q_values_read(monkeypatch):
    # no Q head over the history alone (RL²'s) is built and then replaced
    assert layers_built_and_dropped(monkeypatch, lambda: small_model(CueMemoryEnv())) == []
    net = small_model(CueMemoryEnv()).q_net
    assert net.head.value.in_features == net.q_hidden[0].out_features  # the head reads [e(s); e(i); z]


def test_q_hidden_dim_takes_several_layers_that_train_save_and_load(tmp_path):
    model = small_model(CueMemoryEnv(), learning_starts=10, policy_kwargs={**SMALL_NET, "q_hidden_dim": (24, 12)})
    linears = [m for m in model.q_net.q_hidden if isinstance(m, th.nn.Linear)]
    in_dim = model.q_net.current_embedder.embed_dim + model.q_net.z_dim
    assert [(m.in_features, m.out_features) for m in linears] == [(in_dim, 24), (24, 12)]
    assert model.q_net.head.value.in_features == 12
    before = [m.weight.detach().clone() for m in linears]
    model.learn(40)
    assert all(not th.equal(b, m.weight) for b, m in zip(before, linears))  # both layers train
    model.save(tmp_path / "deep.zip")
    loaded = IMPORT.load(tmp_path / "deep.zip")
    for key, value in model.policy.state_dict().items():
        assert th.equal(value, loaded.policy.state_dict()[key]), key
    for bad in ((), (24, 0), 0, 12.5, True):
        with pytest.raises(ValueError, match="q_hidden_dim must be a non-empty list or tuple of positive ints"):
            small_model(CueMemoryEnv(), policy_kwargs={**SMALL_NET, "q_hidden_dim": bad})


def test_every_saved_parameter_but_the_targets_is_trained():
    model = small_model(CueMemoryEnv(), learning_starts=10)
    model.learn(40)
    batch = model.replay_buffer._get_samples(np.arange(4))
    # both choices of z: e(T) is trained through the Q-values of the sequences that act on it
    batch = batch._replace(use_problem=th.tensor([True, False, True, False]))
    assert keys_without_gradient(model, batch) == []


def test_sb3_argument_and_bad_input_errors():
    with pytest.raises(ValueError, match="SB3's 'exploration_fraction'.*exploration_steps"):
        IMPORT("MetaBus-v0", exploration_fraction=0.1)
    with pytest.raises(TypeError, match="learnin_starts"):
        IMPORT("MetaBus-v0", learnin_starts=10)
    with pytest.raises(ValueError, match="aux_loss_coef must be a number >= 0"):
        IMPORT(CueMemoryEnv(), aux_loss_coef=-1.0)
    with pytest.raises(ValueError, match="replay_buffer_class must be a subclass of .*ProblemSequenceReplayBuffer"):
        IMPORT(CueMemoryEnv(), replay_buffer_class=SequenceReplayBuffer)
    with pytest.raises(ValueError, match="IMPORT needs a trial env"):
        IMPORT(RL2ObservationWrapper(gym.make("CartPole-v1")))
    with pytest.raises(ValueError, match="policy="):
        IMPORT("MlpLstmPolicy", CueMemoryEnv())
    with pytest.raises(ValueError, match="CnnLstmPolicy needs an image"):
        IMPORT("CnnLstmPolicy", CueMemoryEnv())
    with pytest.raises(ValueError, match="env is required"):
        IMPORT("MultiInputLstmPolicy")
    with pytest.raises(ValueError, match="sequence_length"):
        IMPORT(CueMemoryEnv(), sequence_length=0)
    model = small_model(CueMemoryEnv())
    with pytest.raises(ValueError, match="state must be"):
        model.predict(model.env.reset(), state=(np.zeros((1, 2, 16)), np.zeros((1, 2, 16))))
    with pytest.raises(ValueError, match="has the key 'n_exec_episodes'|n_exec_episodes"):
        model.set_env(CueMemoryEnv(n_exec_episodes=2))


# ---------------------------------------------------------------------- alternation and losses
def test_z_alternates_per_trial_and_the_replay_records_problem_and_choice():
    venv = make_vec_env(CueMemoryEnv, n_envs=2, seed=0, wrapper_class=_LogProblems)
    model = small_model(venv, learning_starts=10_000)
    acted = []
    choose = model.q_net.choose_z

    def spy(history, features, use_problem):
        acted.append((features.clone(), use_problem.clone()))
        return choose(history, features, use_problem)

    model.q_net.choose_z = spy
    model.learn(40)  # 20 vectorised steps: 5 trials of 4 steps per env
    buf = model.replay_buffer
    assert buf.size() == 10 and model._n_trials_started == 10
    # trials take e(T) and e(tau) in turn, in the order they start over the envs
    assert buf.use_problem[:10].tolist() == [True, False] * 5
    # each trial's stored problem is the one its env was reset to (env 0's rows are 0, 2, ...)
    logged = [w.problems for w in (venv.envs[0], venv.envs[1])]
    assert buf.problem_ids[0:10:2].tolist() == logged[0][:5] and buf.problem_ids[1:10:2].tolist() == logged[1][:5]
    # the actor used the same choice and problem on every step of a trial
    for k, (features, use) in enumerate(acted):
        trial = k // 4
        assert use.tolist() == [bool(buf.use_problem[2 * trial]), bool(buf.use_problem[2 * trial + 1])]
        assert features[:, 0].tolist() == [logged[0][trial], logged[1][trial]]


def test_loss_equals_the_hand_computation_of_each_sequences_z_and_the_aux_loss():
    model = small_model(CueMemoryEnv(), learning_starts=10, aux_loss_coef=0.5, gamma=0.9)
    model.learn(60)
    batch = model.replay_buffer._get_samples(np.array([0, 1, 2, 3, 4]))
    assert isinstance(batch, ProblemSequenceSamples) and batch.use_problem.tolist() == [True, False, True, False, True]
    batch = batch._replace(use_problem=th.tensor([True, False, False, True, True]))  # both choices, any order
    loss, logged = model._loss(batch)
    net, target = model.q_net, model.q_net_target
    td_errors, aux = [], 0.0
    for b in range(5):
        n = int(batch.lengths[b])
        feats = th.as_tensor(model.problem_table[[int(batch.problem_ids[b])]])
        per_net = []
        for q_net in (net, target):
            states, qs, hs = q_net.initial_states(1), [], []
            for t in range(n + 1):  # step by step from zeros, as the actor does
                obs = {k: v[[b], t] for k, v in batch.observations.items()}
                h, states = q_net.encode_step(obs, states)
                z = q_net.problem_embedder(feats) if batch.use_problem[b] else h
                qs.append(q_net.q_values(obs, z)[0])
                hs.append(h[0])
            per_net.append((qs, hs))
        (q_on, h_on), (q_tg, _) = per_net
        for t in range(n):
            a_star = int(q_on[t + 1].argmax())
            y = batch.rewards[b, t] + 0.9 * (1 - batch.dones[b, t]) * q_tg[t + 1][a_star]
            td_errors.append((q_on[t][batch.actions[b, t]] - y) ** 2)
            aux = aux + ((h_on[t] - net.problem_embedder(feats)[0]) ** 2).sum()
    td = th.stack(td_errors).mean()
    aux = aux / 5  # mean over the batch of the sum over steps and units
    assert logged["td_loss"].item() == pytest.approx(td.item(), rel=1e-4)
    assert logged["aux_loss"].item() == pytest.approx(aux.item(), rel=1e-4)
    assert loss.item() == pytest.approx(td.item() + 0.5 * aux.item(), rel=1e-4)
    # e(T) is a fixed target of the auxiliary loss: its gradient reaches e(tau) only
    model.policy.optimizer.zero_grad()
    history = th.randn(2, 3, 16, requires_grad=True)
    e_problem = th.randn(2, 16, requires_grad=True)
    mask = th.tensor([[1.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    value = import_aux_loss(history, e_problem, mask)
    expected = (((history[0, :2] - e_problem[0]) ** 2).sum() + ((history[1, 0] - e_problem[1]) ** 2).sum()) / 2
    assert value.item() == pytest.approx(expected.item(), rel=1e-6)
    value.backward()
    assert e_problem.grad is None and history.grad[0, 2].abs().sum() == 0 and history.grad[0, :2].abs().sum() > 0


# ---------------------------------------------------------------------- meta-test: the history only
def test_problem_id_never_reaches_the_networks_at_meta_test():
    model = small_model(gym.make("MetaBus-v0"))
    generator = th.Generator().manual_seed(0)
    with th.no_grad():  # weights that make the actions depend on the observations
        for p in model.policy.parameters():
            p.copy_(th.randn(p.shape, generator=generator))
    logs = []
    for scramble in (False, True):
        log = {}
        envs = [_RecordActions(gym.make("MetaBus-v0", split="test"), log) for _ in range(3)]
        if scramble:
            envs = [_ScrambleProblemId(env) for env in envs]
        evaluate_meta(model, envs, n_trials=6, seed=1, n_envs=3)
        logs.append(log)
    assert logs[0] == logs[1] and len({tuple(a) for a in logs[0].values()}) > 1

    def forbidden(*args, **kwargs):
        raise AssertionError("e(T) was used at meta-test")

    model.q_net.problem_embedder.forward = forbidden
    evaluate_meta(model, "MetaBus-v0", n_trials=4, n_envs=2)
    model.predict(model.env.reset(), deterministic=True)


def test_diagnose_meta_tests_on_the_history_and_acts_on_the_problem_code_when_asked():
    model = small_model(gym.make("MetaBus-v0"))
    generator = th.Generator().manual_seed(0)
    with th.no_grad():  # weights that make the actions depend on the observations and on z
        for p in model.policy.parameters():
            p.copy_(th.randn(p.shape, generator=generator))
    problems = [3, 40, 41, 100, 200, 7]
    meta_test = evaluate_meta(model, "MetaBus-v0", n_trials=6, seed=2, problem_ids=problems, n_envs=3)
    runs = []
    for permute in (False, True):
        if permute:  # e(T) of each problem now embeds another problem's features
            model.problem_table = model.problem_table[np.random.default_rng(0).permutation(len(model.problem_table))]
        log = {}
        envs = [_RecordActions(gym.make("MetaBus-v0", split="test"), log) for _ in range(3)]
        runs.append((diagnose(model, envs, n_trials=6, seed=2, problem_ids=problems), log))
    (plain, plain_log), (permuted, permuted_log) = runs
    # z = e(tau): meta-test itself, whatever the problem table
    assert plain.return_history == permuted.return_history == meta_test.mean
    assert plain.exploration_length == meta_test.mean_exploration_length and plain.n_trials == 6
    # z = e(T): the problem's features reach the actions
    assert plain_log != permuted_log
    assert plain.distance_exploration != permuted.distance_exploration
    assert 0 < plain.distance_execution and 0 < plain.problem_spread
    with pytest.raises(TypeError, match="IMPORT model"):
        diagnose(RL2DQN(gym.make("MetaBus-v0")), "MetaBus-v0")
    # exhaustive: every held-out (problem, instruction) pair, weighted as evaluate_meta weights them
    model = small_model(gym.make("MetaBus-v0", variant="map"))
    exact = diagnose(model, "MetaBus-v0", n_trials=4, n_envs=4, exhaustive=True, env_kwargs={"variant": "map"})
    meta_test = evaluate_meta(model, "MetaBus-v0", n_trials=4, n_envs=4, exhaustive=True, env_kwargs={"variant": "map"})
    assert exact.return_history == pytest.approx(meta_test.mean) and exact.n_trials == meta_test.n_trials


class _CurrentProblem(gym.Wrapper):
    """Keeps the problem of the trial the env is playing (from the reset ``info``)."""

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.problem = info["problem_id"]
        return obs, info


def test_diagnose_gives_each_trial_its_own_problems_code():
    model = small_model(gym.make("MetaBus-v0"))
    envs = [_CurrentProblem(gym.make("MetaBus-v0", split="test")) for _ in range(3)]
    problems = [3, 40, 41, 100, 200, 7, 9]
    calls = []

    def features_of(ids):  # what the agent asks e(T) of, beside what each env plays
        calls.append((np.asarray(ids).tolist(), [getattr(env, "problem", None) for env in envs]))
        return th.as_tensor(model.problem_table[np.asarray(ids)])

    model._problem_features = features_of
    diagnose(model, envs, n_trials=7, seed=1, problem_ids=problems, n_envs=3)
    steps = [(asked, played) for asked, played in calls if len(asked) == len(envs)]  # not the split's table
    assert len(steps) > 2 * 20 and all(asked == played for asked, played in steps)
    assert {p for asked, _ in steps for p in asked} == set(problems)  # trials of unequal length end apart


def test_save_load_same_actions_vec_envs_and_callbacks(tmp_path):
    venv = make_vec_env(CueMemoryEnv, n_envs=2, seed=0)
    model = small_model(venv, learning_starts=10)
    ckpt = CheckpointCallback(save_freq=20, save_path=str(tmp_path / "ckpt"), name_prefix="import")
    model.learn(80, callback=ckpt)
    assert model._n_updates > 0 and (tmp_path / "ckpt" / "import_40_steps.zip").exists()
    model.save(tmp_path / "import.zip")
    loaded = IMPORT.load(tmp_path / "import.zip", env=make_vec_env(CueMemoryEnv, n_envs=3))
    assert np.array_equal(loaded.problem_table, model.problem_table) and loaded._n_trials_started == 10 * 2
    env = CueMemoryEnv(n_exec_episodes=2)
    obs, _ = env.reset(seed=3)
    s1 = s2 = None
    for t in range(6):
        a1, s1 = model.predict(obs, s1, np.array([t == 0]), deterministic=True)
        a2, s2 = loaded.predict(obs, s2, np.array([t == 0]), deterministic=True)
        assert a1 == a2 and np.array_equal(s1[0], s2[0])
        obs, *_ = env.step(int(a1))
    loaded.learn(30, reset_num_timesteps=False)  # training goes on with 3 envs
    assert loaded._n_updates > model._n_updates
    assert evaluate_meta(loaded, CueMemoryEnv(split="test"), n_trials=4).returns.shape[0] == 4


def test_image_observations_and_exploration_with_rewards():
    model = small_model(make_vec_env(CueMemoryEnv, n_envs=2, env_kwargs=dict(image=True)), policy="CnnLstmPolicy")
    assert model.q_net.current_embedder.embedders["obs"].embed_dim == 128
    model.learn(40)
    # E-RL² style: the exploration episode has an instruction and rewards
    env = gym.make("MetaBandit-v0", n_actions=2, horizon=1, reward_free_exploration=False)
    model = small_model(env, learning_starts=4)
    model.learn(40)
    assert model._n_updates > 0 and model.replay_buffer.rewards[: model.replay_buffer.size(), 0].any()
    assert evaluate_meta(model, "MetaBandit-v0", n_trials=4, env_kwargs=dict(
        n_actions=2, horizon=1, reward_free_exploration=False)).returns.shape[0] == 4  # fmt: skip


# ---------------------------------------------------------------------- learning
@pytest.mark.slow
def test_import_solves_a_memory_task():
    """The cue is visible only mid-exploration: z = e(tau) must carry it; meta-tested on the history alone.

    A smaller auxiliary weight than the authors' 1 (measured, seed 0: 1.0 after 4000 steps with 0.1;
    0.71 with 1, whose summed loss dominates the TD loss early on)."""
    model = IMPORT(
        make_vec_env(CueMemoryEnv, n_envs=2, seed=0),
        learning_starts=500,
        train_freq=1,
        target_update_interval=200,
        learning_rate=1e-3,
        buffer_size=2000,
        exploration_steps=2000,
        exploration_final_eps=0.05,
        aux_loss_coef=0.1,
        seed=0,
        policy_kwargs=dict(
            lstm_hidden_size=32,
            fusion_dim=32,
            q_hidden_dim=32,
            problem_hidden_dim=32,
            embed_kwargs=dict(per_dim=8, state_hidden_dims=(32, 32), instruction_embed_dim=8),
        ),
    )
    model.learn(4000)
    result = evaluate_meta(model, CueMemoryEnv(split="test"), n_trials=100)
    assert result.mean >= 0.9
    # the auxiliary loss brought the history's code near the problem's, and both codes serve
