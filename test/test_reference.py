"""
docs/REFERENCE.md is what the node declares (``dgp_ros.apps.reference``), and cannot drift.

The generator reads the parameters off their tables, the topics, services and QoS off an
estimator node made in the test's process, the /diagnostics keys off its status; a topic the
node creates without a description, or a description of a topic it does not create, is an
error. Regenerate: ``python -m dgp_ros.apps.reference > docs/REFERENCE.md``.
"""
import os

import pytest

from dgp_ros.apps import reference

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.ros
def test_the_reference_is_what_the_node_declares():
    text = reference.reference()
    with open(os.path.join(REPO, 'docs', 'REFERENCE.md')) as f:
        assert f.read() == text, 'regenerate: python -m dgp_ros.apps.reference > docs/REFERENCE.md'
    # every estimator parameter, topic and a few keys are in it
    from dgp_ros.online.config import NODE_PARAMS, PARAMS
    for name in list(PARAMS) + list(NODE_PARAMS):
        assert f'| `{name}` |' in text, name
    for topic in reference.TOPICS:
        assert f'`{topic}`' in text, topic
    for key in ('effort_gain', 'guarantee', 'rejected/bad_text', 'stamp_to_answer_p99_s'):
        assert f'`{key}`' in text, key


@pytest.mark.ros
def test_a_topic_without_its_line_or_a_line_without_its_topic_is_an_error(monkeypatch):
    less = dict(reference.TOPICS)
    del less['/dgp_estimator/rigid_body_correction']
    monkeypatch.setattr(reference, 'TOPICS', less)
    with pytest.raises(ValueError, match='does not describe'):
        reference.reference()
    monkeypatch.setattr(reference, 'TOPICS', dict(reference.TOPICS, **{'/gone': 'x'}) | {
        '/dgp_estimator/rigid_body_correction': 'y'})
    with pytest.raises(ValueError, match='not created by the node'):
        reference.reference()
