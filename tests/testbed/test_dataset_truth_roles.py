"""Mutation audit 3: a case of `testbed generate` is recognised by its generator meta OR
by its dataset index; either alone must make load refuse a truth entry marked as
observation. The existing test has both, so `or` -> `and` passed."""
import json

import numpy as np
import pytest

from reglib.geometry import RigidTransform
from testbed.dataset import load, write_case


def _case(tmp_path, *, generator: bool, index: bool):
    root = tmp_path / "ds"
    meta = {"views": ["view0"]}
    if generator:
        meta["generator"] = "testbed generate"
    case = {"meta": meta,
            "arrays": {"flags": np.arange(4, dtype=np.int64)},
            "transforms": {"ct2robot": RigidTransform.from_rotvec([0.1, 0.0, 0.0],
                                                                  [1.0, 2.0, 3.0])}}
    # written by hand with the truth transform marked observation (a tampered case)
    write_case(root / "case_0000", case, truth=())
    if index:
        (root / "dataset.json").write_text(json.dumps({"cases": ["case_0000"]}))
    return root / "case_0000"


@pytest.mark.parametrize("generator,index", [(True, False), (False, True)])
def test_truth_entry_marked_observation_is_refused(tmp_path, generator, index):
    case_dir = _case(tmp_path, generator=generator, index=index)
    with pytest.raises(ValueError, match="ground truth but is marked 'observation'"):
        load(case_dir, verify=False)


def test_a_hand_written_case_may_name_freely(tmp_path):
    obs, _ = load(_case(tmp_path, generator=False, index=False), verify=False)
    assert "ct2robot" in obs.transforms
