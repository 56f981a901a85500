"""What the demonstration-task loss names: whole tasks or their parts (object, target)."""

import pytest
import torch
import torch.nn.functional as F

from studio.data.splits import load_split
from studio.model.demo_task import demo_task_loss, label_table


def test_whole_task_labels_are_the_task_index():
    tasks = load_split("pick_place").tasks("train")
    assert label_table(tasks, "task") == ((14,), ())
    logits = torch.randn(5, 14, generator=torch.Generator().manual_seed(0))
    labels = torch.tensor([0, 3, 13, 7, 7])
    loss, right = demo_task_loss(logits, labels, (), ())
    assert torch.allclose(loss, F.cross_entropy(logits, labels))
    assert torch.equal(right, logits.argmax(-1) == labels)


def test_parts_name_the_object_and_the_target_so_a_held_out_pair_has_a_name():
    train = load_split("pick_place").tasks("train")
    groups, table = label_table(train, "parts")
    assert groups == (4, 4) and len(table) == 14
    parts = dict(zip(train, table))
    objects = {name.split("/")[1].split("->")[0]: row[0] for name, row in parts.items()}
    targets = {name.split("->")[1]: row[1] for name, row in parts.items()}
    assert len(set(objects.values())) == 4 and len(set(targets.values())) == 4
    for name, (o, t) in parts.items():  # every row is its own object and target
        assert objects[name.split("/")[1].split("->")[0]] == o and targets[name.split("->")[1]] == t
    # bar->yellow (held out) is bar (from bar->red, bar->green) and yellow (from cube->yellow, ...)
    assert "bar" in objects and "yellow" in targets

    push = load_split("push").tasks("train")  # red-forward, red-backward, blue-forward
    groups, table = label_table(push, "parts")
    assert groups == (2, 2) and table == ((0, 0), (0, 1), (1, 0))


def test_parts_refuse_tasks_that_have_none():
    with pytest.raises(ValueError, match=r"object and a target.*metaworld/button-press"):
        label_table(["metaworld/button-press-v3", "metaworld/door-lock-v3"], "parts")
    with pytest.raises(ValueError, match="synthetic/target0"):
        label_table(["synthetic/target0", "synthetic/target1"], "parts")
    with pytest.raises(ValueError, match="one target only"):
        label_table(["push/red-forward", "push/blue-forward"], "parts")
    with pytest.raises(ValueError, match="unknown demonstration-task labelling"):
        label_table(["push/red-forward"], "colour")


def test_the_parts_loss_is_the_mean_over_groups_and_right_needs_every_group():
    logits = torch.tensor([[4.0, 0.0, 0.0, 4.0], [4.0, 0.0, 4.0, 0.0]])  # groups (2, 2)
    table = ((0, 0), (0, 1), (1, 0))
    tasks = torch.tensor([1, 1])  # object 0, target 1
    loss, right = demo_task_loss(logits, tasks, (2, 2), table)
    expected = (
        F.cross_entropy(logits[:, :2], torch.tensor([0, 0]))
        + F.cross_entropy(logits[:, 2:], torch.tensor([1, 1]))
    ) / 2
    assert torch.allclose(loss, expected)
    assert right.tolist() == [True, False]  # the second names the object but not the target
    with pytest.raises(ValueError, match="need 5"):
        demo_task_loss(logits, tasks, (2, 3), table)


def test_class_names_read_the_classes_back():
    from studio.model.demo_task import class_names

    push = load_split("push").tasks("train")
    assert class_names(push, label_table(push, "parts")[1]) == [["red", "blue"], ["forward", "backward"]]
    assert class_names(push, ()) == [["red-forward", "red-backward", "blue-forward"]]


def test_task_parts_read_from_the_names_match_the_simulators_tasks():
    from studio.model.demo_task import task_parts
    from studio.sim.tasks import get_task, list_tasks

    for name in list_tasks("pick_place") + list_tasks("push"):
        task = get_task(name)
        assert task_parts(name) == (task.obj, task.target), name
    assert task_parts("metaworld/button-press-v3") is None
    assert task_parts("push/red-sideways") is None and task_parts("pick_place/cube") is None
