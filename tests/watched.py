"""The hand-made watched problem the monitor tests share (tests/test_monitor.py,
tests/test_stealth_reports.py): its values are worked out by hand where it is used."""

# From s0 the robot plays a and lands in s1 or s2 (1/2 each). It plays a on o0 and g, b on
# anything else: b is safe everywhere; a is not (s1: trap 0.3, s2: trap 1). Altering o2 -> o0
# (cost 1) makes it play a at s2: 0.5, the unconstrained optimum at budget 1 (o2 -> g costs 2;
# o1 -> o0 and o1 -> g give 0.5 * 0.3 = 0.15). The monitor knows o0 is only read at the start:
# an o0 after it raises the alarm. So o2 -> o0 (and o1 -> o0) are caught whenever the robot
# is in the altered region, with probability 1/2, before it falls; o1 -> g is not: the
# stealthy optimum is 0.15.
HAND = {
    "format": "misdirect/v1",
    "name": "watched",
    "pomdp": {
        "states": ["s0", "s1", "s2", "goal", "trap"],
        "actions": ["a", "b"],
        "initial": "s0",
        "observe": {"s0": "o0", "s1": "o1", "s2": "o2", "goal": "g", "trap": "g"},
        "transitions": [
            ["s0", "a", "s1", 0.5],
            ["s0", "a", "s2", 0.5],
            ["s0", "b", "s0", 1.0],
            ["s1", "a", "trap", 0.3],
            ["s1", "a", "goal", 0.7],
            ["s1", "b", "goal", 1.0],
            ["s2", "a", "trap", 1.0],
            ["s2", "b", "goal", 1.0],
        ],
        "absorbing": ["goal", "trap"],
    },
    "controller": {
        "nodes": ["n"],
        "initial": "n",
        "rules": [
            {"node": "n", "obs": "o0", "action": "a", "next": "n"},
            {"node": "n", "obs": "g", "action": "a", "next": "n"},
            {"node": "n", "obs": "*", "action": "b", "next": "n"},
        ],
    },
    "deception": {
        "decoy": ["trap"],
        "budget": 1,
        "cost": {"pairs": {"o2": {"g": 2}}, "protected": ["g"]},
    },
}
HAND_MONITOR = {
    "states": ["start", "run", "caught"],
    "initial": "start",
    "alarm": ["caught"],
    "transitions": [
        {"state": "start", "reading": "*", "next": "run"},
        {"state": "run", "reading": "o0", "next": "caught"},
        {"state": "run", "reading": ["o1", "o2", "g"], "next": "run"},
    ],
}
WATCHED = {**HAND, "monitor": HAND_MONITOR}  # the problem with its monitor in the file
