"""Training's refinement of the per-frame parameters: per-row Adam, one step per visit of a frame (issue #27)."""

from __future__ import annotations

import torch

from geoavatar.train.frame_params import RowAdam


def visit(optimizer, table: torch.nn.Parameter, row: int, grad: torch.Tensor) -> None:
    """One training step that drew frame `row`: its row of the table gets `grad`, every other row zeros."""
    optimizer.zero_grad()
    table.grad = torch.zeros_like(table)
    table.grad[row] = grad
    optimizer.step()


def test_a_visit_moves_its_row_by_the_rate_and_nothing_moves_between_visits():
    table = torch.nn.Parameter(torch.zeros(4, 3))  # [T, n]
    optimizer = RowAdam([{"params": [table], "lr": 1e-3}])
    visit(optimizer, table, 1, torch.tensor([2.0, -0.5, 0.0]))
    moved = table.detach().clone()
    # the first visit is one Adam step of that row: exactly the rate against the gradient's sign (0 where it is 0)
    assert torch.allclose(moved[1], torch.tensor([-1e-3, 1e-3, 0.0]), atol=1e-9)
    assert moved[[0, 2, 3]].eq(0).all()
    for _ in range(5):  # other frames drawn: the row keeps its place (torch's Adam would drift on its momentum)
        visit(optimizer, table, 2, torch.tensor([1.0, 1.0, 1.0]))
    assert torch.equal(table.detach()[1], moved[1])
    assert torch.allclose(table.detach()[2], torch.full((3,), -5e-3), atol=1e-6)  # five visits, five steps

    dense = torch.nn.Parameter(torch.zeros(4, 3))
    adam = torch.optim.Adam([dense], lr=1e-3)
    visit(adam, dense, 1, torch.tensor([2.0, -0.5, 0.0]))
    after_visit = dense.detach().clone()
    visit(adam, dense, 2, torch.tensor([1.0, 1.0, 1.0]))
    assert not torch.equal(dense.detach()[1], after_visit[1])  # why: the dense optimiser moves a row it did not draw


def test_row_adam_given_a_torch_adam_state_starts_fresh_row_moments():
    table = torch.nn.Parameter(torch.zeros(3, 2))
    adam = torch.optim.Adam([{"params": [table], "lr": 1e-3}])
    visit(adam, table, 0, torch.tensor([1.0, 1.0]))
    row_adam = RowAdam([{"params": [table], "lr": 1e-3}])
    row_adam.load_state_dict(adam.state_dict())
    before = table.detach().clone()
    visit(row_adam, table, 2, torch.tensor([-1.0, 0.5]))
    assert torch.allclose(table.detach()[2] - before[2], torch.tensor([1e-3, -1e-3]), atol=1e-9)
    assert torch.equal(table.detach()[:2], before[:2])


def test_a_checkpoint_of_torchs_adam_resumes_with_torchs_adam_and_a_new_run_gets_row_adam():
    from geoavatar.config import LearningRates
    from geoavatar.train.frame_params import FrameParams
    from geoavatar.train.state import tracking_optimizer

    params = {"expr": torch.zeros(3, 4), "rotation": torch.zeros(3, 3), "neck_pose": torch.zeros(3, 3),
              "jaw_pose": torch.zeros(3, 3), "eyes_pose": torch.zeros(3, 6), "translation": torch.zeros(3, 3),
              "shape": torch.zeros(5)}
    frames = FrameParams(params)
    lr = LearningRates()
    old = torch.optim.Adam(frames.param_groups(lr), lr=0.0)
    for value in frames.values.values():
        value.grad = torch.ones_like(value)
    old.step()  # a run trained before RowAdam: its checkpoint holds torch Adam's state
    assert type(tracking_optimizer(frames, lr, old.state_dict())) is torch.optim.Adam  # resumes as it was trained
    assert isinstance(tracking_optimizer(frames, lr), RowAdam)  # a new run
    row = RowAdam(frames.param_groups(lr), lr=0.0)
    row.step()
    assert isinstance(tracking_optimizer(frames, lr, row.state_dict()), RowAdam)  # a run trained with it
    assert tracking_optimizer(FrameParams(params, refine=False), lr) is None
