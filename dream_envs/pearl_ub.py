"""PEARL-UB: the expected execution return of Thompson sampling with the true posterior and
optimal problem-specific policies (paper, Section 6), computed exactly for each trial env.

The paper defines PEARL-UB as "the analytically computed expected rewards achieved by the optimal
problem-specific policy that explores via Thompson Sampling (TS) with the true posterior problem
distribution, which is an upperbound on the final performance of PEARL". TS acts in every episode
of a trial, the exploration episode included: it samples a problem from its posterior and acts
for the whole episode with that problem's optimal policy; the posterior conditions on everything
the trial has shown so far. So, in a trial of one exploration and one execution episode:

1. *Exploration.* Nothing has been seen yet: TS samples a problem T1 from the prior and, as the
   reward-free exploration episode has no instruction, an instruction i1 from the prior too
   (``(T1, i1) ~ p(T, i)``), and runs the optimal policy of T1 for i1 in the true problem T. The
   episode is reward-free, but its states show T's dynamics where the policy goes: which
   destination the ridden bus reaches, what a fridge gives. With ``rewarded_exploration=True``
   (the paper's dashed-line setting, the envs' ``reward_free_exploration=False``) the exploration
   episode has its own instruction i_exp, drawn like an execution one, and rewards: TS samples T1
   from p(T | i_exp), runs its policy for i_exp, and also sees the rewards.
2. *Execution.* With instruction i, TS samples T2 from the true posterior
   ``p(T' | exploration, i)``: proportional to ``p(T') p(i | T')`` (times ``p(i_exp | T')``) over
   the problems T' under which the exploration episode would have shown the same thing. It runs
   the optimal policy of T2 for i in T, without revising the guess within the episode (PEARL holds
   one posterior sample per episode); PEARL-UB is the expected return of that execution episode.

    PEARL-UB = sum_{T, i} p(T, i) sum_{T1, i1} p(T1, i1) sum_{T2} p(T2 | o_T(T1, i1), i) R_T(pi*_{T2}, i)

where p(T, i) is the split's trial distribution (:meth:`~dream_envs.trial_env.TrialEnv.trial_cases`:
a problem uniformly from the split, then an instruction uniformly from the problem's), o_T(T1, i1)
what the exploration policy of (T1, i1) shows in T, and R_T(pi*_{T2}, i) the return of one
execution episode of T2's optimal policy in T. :func:`pearl_ub` enumerates all of it exactly.

Why this reading: the paper says TS *explores*, with the *true posterior*, and that on the bus it
"only explores one bus per episode (and never reads the map)": the exploration episode is played
by a sampled problem's optimal policy, which rides one bus, and what it sees there informs the
posterior. Its SignNav3D sentence, that PEARL-UB "does not achieve maximal reward, even when it
receives rewards during exploration", reads the reward-free line as the main one and the rewarded
one as the dashed setting. (An earlier reading of this module, in which the reward-free
exploration episode tells TS nothing, is what Thompson sampling from rewards alone would get; it
is lower on every env, see ``docs/baselines.md``.)

Conventions that make "the optimal policy" a single policy where it has choices:

* Where the optimal policy of T1 has several optimal actions that lead to different outcomes
  (MetaCook's two corner fridges holding the same ingredient), each is taken with equal
  probability; TS knows which it took.
* Where every action ties because the sampled task is done or can no longer be done in the
  episode (a bus ridden to the wrong destination near the horizon, the goal reached in a
  reward-free exploration episode), the policy takes the end-episode action. This costs what any
  other action would (``-0.1`` per step left), so execution returns are those of any optimal
  policy, and it keeps the exploration from revealing things by a tie's accident.

Each env's derivation is in the docstring of its ``_*_rules`` function below.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from typing import Callable, Dict, Hashable, List, Optional, Sequence, Tuple


from dream_envs.trial_env import TrialEnv

Instruction = Tuple[int, ...]
# (weight, behaviour): how the optimal policy of a problem acts on an instruction.
Behaviours = List[Tuple[float, Hashable]]


@dataclasses.dataclass(frozen=True)
class ThompsonRules:
    """An env's rules for PEARL-UB.

    :param behaviours: ``behaviours(problem, instruction)``: the ways (with probabilities) the
        optimal policy of ``problem`` acts on ``instruction``, as hashable summaries of what matters
        about them (e.g. which bus it rides).
    :param execution_return: ``execution_return(true, behaviour, instruction)``: the return of an
        execution episode in which the policy acts as ``behaviour`` in the true problem.
    :param observe: ``observe(true, behaviour, instruction, rewarded)``: what an exploration
        episode in which the policy acts as ``behaviour`` (for ``instruction``) shows in the true
        problem (hashable; equal values for problems it cannot tell apart); ``rewarded``: the
        episode has rewards (``rewarded_exploration``).
    """

    behaviours: Callable[[int, Instruction], Behaviours]
    execution_return: Callable[[int, Hashable, Instruction], float]
    observe: Callable[[int, Hashable, Instruction, bool], Hashable]


def pearl_ub(env, split: str = "test", rewarded_exploration: Optional[bool] = None) -> float:
    """PEARL-UB of a trial env (or a wrapper of one) on ``split``: the expected return of the
    execution episode of Thompson sampling with the true posterior and optimal problem-specific
    policies, which also acts in the exploration episode (see this module's docstring). Exact: an
    enumeration, not a simulation.

    :param env: a MetaBandit, MetaBus, MetaCook or SignNav3D trial env.
    :param split: the split whose trial distribution is the prior (and the trials).
    :param rewarded_exploration: the exploration episode has an instruction and rewards (the
        paper's dashed-line setting); default: as the env (``not env.reward_free_exploration``).
    """
    base = env.unwrapped
    rules = thompson_rules(base)
    if rewarded_exploration is None:
        rewarded_exploration = not base.reward_free_exploration
    return thompson_value(rules, base.trial_cases(split), bool(rewarded_exploration))


def thompson_value(
    rules: ThompsonRules,
    cases: Tuple[Sequence[int], Sequence[Sequence[int]], Sequence[float]],
    rewarded_exploration: bool = False,
) -> float:
    """PEARL-UB for the trial distribution ``cases`` = ``(problem_ids, instructions, probabilities)``
    (as :meth:`~dream_envs.trial_env.TrialEnv.trial_cases`: p(T, i) = p(T) p(i | T)) under ``rules``.

    Enumerates the exploration context c (none, or the exploration instruction), the exploration
    plan (behaviour and instruction of TS's exploration policy), the true (problem, execution
    instruction) and the posterior's behaviours, weighting each by its probability."""
    pids, instructions, probabilities = cases
    p_problem: Dict[int, float] = defaultdict(float)
    p_instruction: Dict[int, Dict[Instruction, float]] = defaultdict(dict)
    for k, instruction, p in zip(pids, instructions, probabilities):
        p_problem[int(k)] += float(p)
    for k, instruction, p in zip(pids, instructions, probabilities):
        k = int(k)
        p_instruction[k][tuple(int(v) for v in instruction)] = float(p) / p_problem[k]
    behaviours = {(k, i): rules.behaviours(k, i) for k in p_problem for i in p_instruction[k]}
    returns: Dict[Tuple[int, Hashable, Instruction], float] = {}

    def execution_return(true: int, behaviour: Hashable, instruction: Instruction) -> float:
        key = (true, behaviour, instruction)
        if key not in returns:
            returns[key] = float(rules.execution_return(true, behaviour, instruction))
        return returns[key]

    if rewarded_exploration:
        # The exploration instruction is drawn like an execution one: TS sees it before acting.
        all_instructions = sorted({i for k in p_instruction for i in p_instruction[k]})
        contexts = [(c, {k: p_problem[k] * p_instruction[k].get(c, 0.0) for k in p_problem}) for c in all_instructions]
    else:
        contexts = [(None, dict(p_problem))]

    total = 0.0
    for context, weights in contexts:
        # weights[T] = p(T) p(c | T): the joint of the true problem and the context, before exploring.
        weights = {k: w for k, w in weights.items() if w > 0}
        norm = sum(weights.values())
        plans: Dict[Tuple[Hashable, Instruction], float] = defaultdict(float)
        for k1, w1 in weights.items():
            own = p_instruction[k1] if context is None else {context: 1.0}
            for i1, q1 in own.items():
                for w, b1 in behaviours[(k1, i1)]:
                    plans[(b1, i1)] += w1 / norm * q1 * w
        for (b1, i1), plan_p in plans.items():
            seen = {k: rules.observe(k, b1, i1, rewarded_exploration) for k in weights}
            # posterior[(o, i)][b2]: the unnormalised posterior mass of the execution behaviour b2.
            posterior: Dict[Tuple[Hashable, Instruction], Dict[Hashable, float]] = defaultdict(
                lambda: defaultdict(float)
            )
            for k2, w2 in weights.items():
                for i, qi in p_instruction[k2].items():
                    for w, b2 in behaviours[(k2, i)]:
                        posterior[(seen[k2], i)][b2] += w2 * qi * w
            for k, wk in weights.items():
                for i, qi in p_instruction[k].items():
                    masses = posterior[(seen[k], i)]
                    mass = sum(masses.values())
                    value = sum(m * execution_return(k, b2, i) for b2, m in masses.items()) / mass
                    total += plan_p * wk * qi * value
    return float(total)


def thompson_rules(env: TrialEnv) -> ThompsonRules:
    """The :class:`ThompsonRules` of a trial env; a TypeError for an env it does not know."""
    from dream_envs.bandit import MetaBanditEnv
    from dream_envs.bus import MetaBusEnv
    from dream_envs.cook.env import MetaCookEnv

    if isinstance(env, MetaBanditEnv):
        return _bandit_rules(env)
    if isinstance(env, MetaBusEnv):
        return _bus_rules(env)
    if isinstance(env, MetaCookEnv):
        return _cook_rules(env)
    if type(env).__name__ == "SignNav3DEnv":  # not imported here: its module needs OpenGL only to build
        return _sign_nav_rules(env)
    raise TypeError(f"pearl_ub does not know {type(env).__name__}; it knows MetaBandit, MetaBus, MetaCook, SignNav3D")


def supports(env) -> bool:
    """Whether :func:`pearl_ub` knows ``env`` (a trial env or a wrapper of one)."""
    try:
        thompson_rules(env.unwrapped)
    except TypeError:
        return False
    return True


def _bandit_rules(env) -> ThompsonRules:
    """MetaBandit (N = |A|^H problems, one instruction): the optimal policy of T1 plays T1's
    sequence. In exploration that shows the problem only if the sequence is a_* = (0, ..., 0),
    i.e. T1 = 0 (the reveal); with rewards, it also shows whether T1 = T (reward 1). In execution
    the guess earns 1 iff it is T.

    Reward-free: with probability 1/N TS explores with a_* and then knows T (1); otherwise the
    posterior is the prior (1/N): PEARL-UB = 1/N + (1 - 1/N)/N (|A| = 2, H = 1: 0.75; |A| = 8:
    15/64). Rewarded: TS knows T if T1 = T or T1 = 0 (probability (2N - 1)/N^2); otherwise the
    posterior is uniform over the N - 1 problems other than T1: PEARL-UB = (2N - 1)/N^2 +
    ((N - 1)^2/N^2)/(N - 1) = (3N - 2)/N^2 (|A| = 2: 1; |A| = 8: 22/64)."""

    def behaviours(problem, instruction):
        return [(1.0, problem)]

    def execution_return(true, guess, instruction):
        return 1.0 if guess == true else 0.0

    def observe(true, guess, instruction, rewarded):
        reveal = true if guess == 0 else None
        return (reveal, guess == true) if rewarded else reveal

    return ThompsonRules(behaviours, execution_return, observe)


def _bus_rules(env) -> ThompsonRules:
    """MetaBus (every variant): for goal g, the optimal policy of a problem T' steps onto the
    colored stop s that T' routes to the destination next to g, rides, and steps onto g (3 steps,
    return 0.8; it never reads the map or rides a gray bus, which would only be slower).

    *Execution* in the true problem T: if T routes s there too, the return is 0.8. Otherwise the ride
    lands on another destination d'. There the policy of T' rides back (T' links d' to another
    stop s'', from which s is 2 steps away: 5 steps to the goal, against at least 7 on foot), but in
    T the bus at d' goes back to s, where the policy of T' rides again: it shuttles between s and d'
    until the goal is out of reach, then ends the episode: -0.1 x horizon (-2.0 at 20 steps).

    *Exploration* (the policy of (T1, g1)): the same path, so the episode shows where T's bus at s1
    = s(T1, g1) goes, and nothing else (shuttling rides the same route; at the goal, or once it is
    out of reach, the policy ends the episode). Rewards add nothing to that. So the posterior keeps
    the problems that route s1 as T does.

    With every colored permutation equally likely (map, vanilla, the distracting bus's "all") s1 is
    uniform and independent of T. With probability 1/4 it is the stop of the execution goal g:
    0.8. Otherwise the posterior leaves 3 stops equally likely for g: 0.8 with probability 1/3,
    else -2.0. PEARL-UB = 0.25 x 0.8 + 0.75 x (0.8 / 3 - 2 x 2.0 / 3) = -0.6 (the same with
    rewards: the exploration goal is independent of T). The distracting bus's train and test
    splits weigh the permutations unevenly (IDs 0, 11, 22, ... are train), which the enumeration
    accounts for."""
    from dream_envs.bus import COLORED_STOPS, GOAL_REWARD, STEP_REWARD, goal_stop_destination

    if env.horizon < 3:
        raise ValueError(f"pearl_ub needs a MetaBus horizon of at least 3 steps, got {env.horizon}")
    miss = STEP_REWARD * env.horizon
    hit = GOAL_REWARD + 2 * STEP_REWARD
    n = len(COLORED_STOPS)
    # stop[problem % 24][goal]: the colored stop routed next to the goal (the gray buses play no part).
    stops = {}
    destinations = {}
    for colored in range(24):
        routes = env.routes(colored)
        destinations[colored] = {s: routes[s] for s in COLORED_STOPS}
        stops[colored] = [next(s for s in COLORED_STOPS if routes[s] == goal_stop_destination(g)) for g in range(n)]

    def behaviours(problem, instruction):
        return [(1.0, stops[problem % 24][instruction[0] - 1])]

    def execution_return(true, stop, instruction):
        return hit if stops[true % 24][instruction[0] - 1] == stop else miss

    def observe(true, stop, instruction, rewarded):
        return destinations[true % 24][stop]

    return ThompsonRules(behaviours, execution_return, observe)


def _cook_rules(env) -> ThompsonRules:
    """MetaCook: for recipe (A, B), the optimal policy of a problem T' fetches A from the nearest
    fridge k_A that T' says holds A (the middle one, 1 step from the pot, else a corner one, 2
    steps; when both corners hold it and the middle does not, either, with probability 1/2),
    carries it back, drops it, and does the same for B from k_B: 4 + 2 (d_A + d_B) steps and
    return 1 - 0.2 (d_A + d_B) (0.6, 0.4 or 0.2).

    *Execution* in the true problem T: the above if T holds A in k_A and B in k_B. If T's fridge
    k_A holds X != A, the pickup gives X; the policy of T' picks up again (in T' that would give A
    and +0.25) and keeps doing so until the horizon: every step costs -0.1, return -0.1 x horizon
    (-2.0). If A succeeds and k_B holds X != B, it has earned two stage rewards (+0.25 each) and
    every other step costs -0.1: 0.5 - 0.1 x (horizon - 2) (-1.3).

    *Exploration* (the policy of (T1, (A1, B1)), fridges k_A1, k_B1): the first pickup shows what
    T's fridge k_A1 holds; if it is A1 the policy cooks it and the pickup at k_B1 shows that
    fridge's content; otherwise it picks up at k_A1 again and again, showing nothing new. (Walking
    past a fridge shows nothing; after cooking the policy ends the episode.) Stage rewards follow
    from the same contents, so rewards add nothing. The instruction is drawn from the true
    problem's recipes, so the posterior also keeps only problems that hold the recipe's
    ingredients (weighted by p(i | T'), i.e. by 1 / its number of recipes)."""
    from dream_envs.cook.kitchen import N_FRIDGES, STAGE_REWARD, STEP_REWARD, distance_to_fridge, fridge_contents

    if env.horizon < 12:
        raise ValueError(f"pearl_ub needs a MetaCook horizon of at least 12 steps, got {env.horizon}")
    horizon = env.horizon

    def nearest(contents, ingredient):
        holding = [k for k in range(N_FRIDGES) if contents[k] == ingredient]
        best = min(distance_to_fridge(k) for k in holding)
        return [k for k in holding if distance_to_fridge(k) == best]

    def behaviours(problem, instruction):
        contents = fridge_contents(problem)
        first, second = nearest(contents, instruction[0]), nearest(contents, instruction[1])
        weight = 1.0 / (len(first) * len(second))
        return [(weight, (ka, kb)) for ka in first for kb in second]

    def execution_return(true, fridges, instruction):
        contents = fridge_contents(true)
        (ka, kb), (a, b) = fridges, instruction
        if contents[ka] != a:
            return STEP_REWARD * horizon
        if contents[kb] != b:
            return 2 * STAGE_REWARD + STEP_REWARD * (horizon - 2)
        return 4 * STAGE_REWARD + 2 * STEP_REWARD * (distance_to_fridge(ka) + distance_to_fridge(kb))

    def observe(true, fridges, instruction, rewarded):
        contents = fridge_contents(true)
        (ka, kb), a = fridges, instruction[0]
        return (contents[ka],) if contents[ka] != a else (contents[ka], contents[kb])

    return ThompsonRules(behaviours, execution_return, observe)


def _sign_nav_rules(env) -> ThompsonRules:
    """SignNav3D (analytic: playing it needs OpenGL): the optimal policy of a problem T' (sign
    colour c') walks to the object of colour c' and the instructed type and touches it, which ends
    the episode. It has no reason to look at the sign (the paper: it "does not ever read the sign
    for any instruction or problem"), so it moves the same way in either problem.

    *Execution*: +1 if c' is the sign's colour, -1 otherwise (the wrong-colour object's reward).
    *Exploration*: reward-free, touching the object shows nothing about the sign, so the posterior
    is the prior (the instruction says nothing about the colour) and PEARL-UB = 0.5 x 1 + 0.5 x (-1)
    = 0. With rewards, the touch earns +1 or -1, which tells the colour: the execution episode then
    earns 1, PEARL-UB = 1 for the execution episode. (The paper's remark that PEARL-UB "does not
    achieve maximal reward, even when it receives rewards during exploration" holds for the whole
    trial's return, 0 + 1 of the optimal 2 when exploration rewards count, not for the execution
    return; see ``docs/baselines.md``.) A start from which the object is out of reach within the
    horizon touches nothing in either problem; the rules take every object as reachable."""

    def behaviours(problem, instruction):
        return [(1.0, problem)]

    def execution_return(true, guess, instruction):
        return 1.0 if guess == true else -1.0

    def observe(true, guess, instruction, rewarded):
        return guess == true if rewarded else None

    return ThompsonRules(behaviours, execution_return, observe)


def execution_rules(env: TrialEnv):
    """``(behaviours, execution_return)`` of :func:`thompson_rules` (the execution episode's rules)."""
    rules = thompson_rules(env)
    return rules.behaviours, rules.execution_return


__all__ = ["ThompsonRules", "pearl_ub", "supports", "thompson_rules", "thompson_value", "execution_rules"]
