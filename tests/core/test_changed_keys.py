"""config.changed_keys: the dotted keys a resume refusal names."""

from crchfl_sumo.core.config import changed_keys, changed_keys_text


def test_nested_keys_that_differ_or_are_missing_are_named_in_order():
    old = {"seed": 0, "generate": {"dataset": {"recovery_share": 0.25}}, "towns": [1, 2], "same": {"a": 1}}
    new = {"seed": 0, "generate": {"dataset": {"recovery_share": 0.25, "recovery_red_share": 0.5}}, "towns": [1, 3],
           "same": {"a": 1}, "added": None}
    assert changed_keys(old, new) == ["added", "generate.dataset.recovery_red_share", "towns"]
    assert changed_keys(new, new) == []
    # a table against a plain value is one change, not a walk into the table
    assert changed_keys({"a": {"b": 1}}, {"a": 2}) == ["a"]


def test_the_text_names_the_first_keys_and_counts_the_rest():
    old, new = {k: 0 for k in "abcdef"}, {k: 1 for k in "abcdef"}
    assert changed_keys_text(old, new) == "a, b, c, d and 2 more"
    assert changed_keys_text(old, {**old, "c": 1}) == "c"
