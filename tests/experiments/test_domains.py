"""``experiments/domains.py``: reading a manifest entry's training commands."""

from experiments.domains import entry_pitch_aware


def test_a_manifest_entry_trained_pitch_aware_is_known_by_its_command():
    assert entry_pitch_aware({"train_command": "hrn-pyg train --preset ours --model-pitch-aware true --data d"})
    assert entry_pitch_aware({"train_command": "x", "stage_commands": ["hrn-pyg train --model-pitch-aware on"]})
    assert not entry_pitch_aware({"train_command": "hrn-pyg train --model-pitch-aware false --data d"})
    assert not entry_pitch_aware({})
