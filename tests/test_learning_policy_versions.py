"""Actors load exactly the policy version a step asks for, even when newer weights are already in."""

from learning.policy_versions import WeightsInbox


def test_inbox_loads_the_newest_version_not_above_the_need():
    loaded = []
    inbox = WeightsInbox(lambda blob, v: loaded.append((blob, v)))
    inbox.offer(0, b"w0")
    inbox.offer(1, b"w1")  # the learner is one version ahead of the rollout
    assert inbox.select(0) and loaded == [(b"w0", 0)] and inbox.version == 0
    assert not inbox.select(0)  # nothing newer allowed yet: version 1 stays held
    assert 1 in inbox.held
    inbox.offer(0, b"again")  # a re-published old version is ignored
    inbox.offer(2, b"w2")
    assert inbox.select(2) and loaded[-1] == (b"w2", 2) and inbox.held == {}
    assert inbox.select(None) is False


def test_inbox_without_a_need_takes_the_newest_and_caps_what_it_holds():
    loaded = []
    inbox = WeightsInbox(lambda blob, v: loaded.append(v), keep=2)
    for v in range(5):
        inbox.offer(v, b"x")
    assert sorted(inbox.held) == [3, 4]
    assert inbox.select(None) and loaded == [4]
