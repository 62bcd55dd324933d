"""
Commands to the learner process and their replies (``online.calls``): nothing is held forever.

A reply that comes after its caller gave up (a ``call`` that timed out, a ``call_async`` that
expired) is dropped, so a node whose learner answers late now and then for weeks holds no more
than the calls in flight.
"""
import threading

from dgp_ros.online.process.commands import Calls


def test_a_late_reply_is_dropped_and_nothing_is_held():
    calls, sent = Calls(timeout_s=0.05), []
    ok, why = calls.call(sent.append, 'refit')
    assert not ok and 'in time' in why and calls.held() == 0
    calls.deliver(sent[-1][1], True, 'late')            # the learner answers after all
    assert calls.held() == 0
    got = []
    calls.call_async(sent.append, 'save', got.append, timeout=0.0)
    calls.expire()
    assert got == [(False, 'the learner did not answer in time')] and calls.held() == 0
    calls.deliver(sent[-1][1], True, 'late')
    assert calls.held() == 0 and len(got) == 1


def test_a_reply_in_time_reaches_its_caller():
    calls, sent = Calls(timeout_s=5.0), []

    def answer(msg):
        sent.append(msg)
        threading.Timer(0.02, calls.deliver, args=(msg[1], True, 'done')).start()
    assert calls.call(answer, 'refit') == (True, 'done')
    got = []
    calls.call_async(sent.append, 'save', got.append)
    assert calls.held() == 1
    calls.deliver(sent[-1][1], True, 'saved')
    assert got == [(True, 'saved')] and calls.held() == 0
