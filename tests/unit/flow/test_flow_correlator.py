"""Flow fixes from the tiny-preset diagnosis: cosine cost + soft-argmax correlator, volume inputs."""

import pytest
import torch

from core.models.cost_volume import cross_correlation_3d, displacements, soft_argmax_displacement
from core.models.flow3d import Flow3D


def _soft_argmax_reference(cost, radius, beta):
    """One voxel at a time: weights exp(β·c_d) / Σ exp(β·c_d'), then Σ_d w_d · d."""
    disp = displacements(radius)  # D×3
    B, D, Z, Y, X = cost.shape
    out = torch.zeros(B, 3, Z, Y, X)
    for b in range(B):
        for z in range(Z):
            for y in range(Y):
                for x in range(X):
                    w = torch.exp(beta * cost[b, :, z, y, x].double())
                    out[b, :, z, y, x] = ((w / w.sum())[:, None] * disp.double()).sum(0).float()
    return out


def test_soft_argmax_matches_the_per_voxel_reference_and_checks_the_radius():
    radius = (1, 1, 1)
    cost = torch.randn(2, 27, 3, 2, 4)
    torch.testing.assert_close(soft_argmax_displacement(cost, radius, 3.0), _soft_argmax_reference(cost, radius, 3.0),
                               atol=1e-5, rtol=0)
    with pytest.raises(Exception, match="displacements"):
        soft_argmax_displacement(cost, (2, 1, 1), 3.0)


def test_soft_argmax_gradients_are_the_per_voxel_references():
    """Cost and β gradients through the fast form equal autograd through the voxel loop (a radius that
    differs per axis, so a transposed displacement table would show)."""
    radius = (2, 1, 0)
    cost = torch.randn(2, 15, 2, 3, 4, requires_grad=True)
    beta = torch.tensor(2.5, requires_grad=True)
    weights = torch.randn(2, 3, 2, 3, 4)
    (soft_argmax_displacement(cost, radius, beta) * weights).sum().backward()
    fast = cost.grad.clone(), beta.grad.clone()
    cost.grad, beta.grad = None, None
    (_soft_argmax_reference(cost, radius, beta) * weights).sum().backward()
    torch.testing.assert_close(fast[0], cost.grad, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(fast[1], beta.grad, atol=1e-5, rtol=1e-4)


def test_uniform_cost_gives_zero_motion():
    cost = torch.ones(1, 27, 2, 2, 2)  # empty space: every displacement matches equally
    assert soft_argmax_displacement(cost, (1, 1, 1), 10.0).abs().max() < 1e-6


def test_untrained_module_finds_a_shift_of_one_voxel():
    """The correlator prior works before training: a volume shifted by +1 voxel along x at t+1 (its
    content at p sits at p + (1, 0, 0)) reads as flow +1 x in the interior."""
    torch.manual_seed(0)
    net = Flow3D(in_channels=4, channels=16, levels=2, finest=0, unit_cost=True, soft_argmax=True)
    f0 = torch.randn(1, 4, 12, 8, 12)  # distinctive (zero-mean) content
    f1 = torch.roll(f0, shifts=1, dims=-1)  # f1(p + x̂) = f0(p)
    with torch.no_grad():
        flow = net(f0, f1)["flow"]
    interior = flow[0, :, 3:-3, 3:-3, 3:-4]  # away from the borders and the roll's wrap
    assert abs(float(interior[0].median()) - 1.0) < 0.25
    assert float(interior[1:].abs().median()) < 0.2


def test_volume_inputs_take_four_channels_and_are_in_the_config():
    net = Flow3D(in_channels=4, inputs="volume", unit_cost=True, soft_argmax=True, levels=2, finest=1, refine=True)
    assert net.config()["inputs"] == "volume" and net.config()["refine"] is True
    out = net(torch.rand(1, 4, 8, 4, 8), torch.rand(1, 4, 8, 4, 8))
    assert out["flow"].shape == (1, 3, 8, 4, 8)
    with pytest.raises(ValueError, match="volume"):
        Flow3D(in_channels=8, inputs="volume")


def test_a_module_saved_without_the_correlator_still_loads():
    """Flow3D configs from before the correlator (no unit_cost/soft_argmax/refine keys) build the same
    parameters, so their saved weights load strictly."""
    from core.models.registry import build_module

    old = Flow3D(in_channels=8, channels=4, levels=2, hidden=8)
    config = {k: v for k, v in old.config().items()
              if k in ("in_channels", "channels", "levels", "radius", "hidden", "finest")}
    build_module("flow3d", config).load_state_dict(old.state_dict(), strict=True)


def test_volume_task_trains_the_flow_on_input_volumes():
    from core.data.batch import records_to_batch
    from core.presets import TINY
    from core.synthetic.generate import generate_record
    from core.tasks.flow import FlowTask

    task = FlowTask.from_preset(TINY, seed=0, inputs="volume")
    assert task.flow.config()["inputs"] == "volume" and task.flow.in_channels == 4
    batch = records_to_batch([generate_record(TINY, seed=3, moving_ego=True)])
    x0, x1, occupied = task.flow_inputs(batch, 0)
    assert x0.shape == x1.shape == (1, 4, *TINY.grid.shape_zyx) and occupied.shape == (1, 1, *TINY.grid.shape_zyx)
    torch.testing.assert_close(occupied, task.occupied(batch, 0))
    out = task(batch)
    out["loss"].backward()
    assert torch.isfinite(out["loss"]) and task.flow.refine_zero_bias.grad is not None
    assert all(p.grad is None for p in task.mapper.parameters())  # frozen and not run


def test_task_radius_reaches_every_cost_volume():
    """FlowTaskConfig.radius is the module's window: D = 5·3·5 = 75 costs per level at (2, 1, 2)."""
    from core.data.batch import records_to_batch
    from core.presets import TINY
    from core.synthetic.generate import generate_record
    from core.tasks.flow import FlowTask

    task = FlowTask.from_preset(TINY, seed=0, inputs="volume", radius=(2, 1, 2))
    assert task.flow.config()["radius"] == [2, 1, 2]
    assert task.flow.decoders[0][0].in_channels == 75 + task.flow.channels + 3
    out = task(records_to_batch([generate_record(TINY, seed=3, moving_ego=True)]))
    assert torch.isfinite(out["loss"])


def test_cost_squeeze_feeds_the_decoders_k_channels_and_learns():
    """cost_channels=k: each level's D costs pass a 1×1×1 conv to k channels, so the decoder's first conv
    takes k + C + 3 inputs whatever the window; the squeeze gets gradients and the config round-trips."""
    from core.models.registry import build_module

    net = Flow3D(in_channels=4, channels=4, levels=2, hidden=8, radius=(2, 1, 2), cost_channels=6,
                 unit_cost=True, refine=True, inputs="volume")
    assert all(d[0].in_channels == 6 + 4 + 3 for d in net.decoders)
    assert all(s[0].in_channels == 75 and s[0].out_channels == 6 for s in net.cost_squeeze)
    torch.manual_seed(0)
    f0, f1 = torch.rand(1, 4, 8, 4, 8), torch.rand(1, 4, 8, 4, 8)
    for dec in net.decoders:  # a non-zero last conv, so the squeezed costs reach the flow
        torch.nn.init.normal_(dec[-1].weight, std=0.1)
    net(f0, f1)["flow"].square().sum().backward()
    assert all(s[0].weight.grad is not None and s[0].weight.grad.abs().sum() > 0 for s in net.cost_squeeze)
    rebuilt = build_module("flow3d", net.config())
    rebuilt.load_state_dict(net.state_dict(), strict=True)
    with torch.no_grad():
        torch.testing.assert_close(rebuilt(f0, f1)["flow"], net(f0, f1)["flow"])
    with pytest.raises(ValueError, match="cost_channels"):
        Flow3D(in_channels=4, inputs="volume", cost_channels=-1)


def test_refine_radius_sets_only_the_grid_step_window():
    """refine_radius is the grid refinement's window; decoders keep `radius`. The refinement's soft-argmax
    with window r moves a voxel at most r voxels per axis past the upsampled flow (an untrained module
    has zero decoders, so the whole flow is the refinement's)."""
    net = Flow3D(in_channels=4, channels=4, levels=2, hidden=8, radius=(2, 1, 2), refine_radius=(1, 0, 1),
                 unit_cost=True, refine=True, inputs="volume", beta=1000.0)
    assert net.config()["refine_radius"] == [1, 0, 1] and net.decoders[0][0].in_channels == 75 + 4 + 3
    torch.manual_seed(0)
    with torch.no_grad():
        flow = net(torch.rand(1, 4, 8, 4, 8), torch.rand(1, 4, 8, 4, 8))["flow"]
    assert flow[:, 1].abs().max() == 0  # y window 0
    assert flow[:, 0].abs().max() <= 1 + 1e-5 and flow[:, 2].abs().max() <= 1 + 1e-5
    assert Flow3D(in_channels=4, inputs="volume", radius=(2, 1, 2)).refine_radius == (2, 1, 2)  # default: radius
    with pytest.raises(ValueError, match="refine_radius"):
        Flow3D(in_channels=4, inputs="volume", refine_radius=(1, -1, 1))


def test_a_module_saved_before_the_squeeze_and_refine_radius_loads():
    """Configs without cost_channels / refine_radius (bundles made before them) build the same module."""
    from core.models.registry import build_module

    old = Flow3D(in_channels=8, channels=4, levels=2, hidden=8, radius=(2, 1, 2), refine=True, unit_cost=True)
    config = {k: v for k, v in old.config().items() if k not in ("cost_channels", "refine_radius", "refine_aggregate")}
    rebuilt = build_module("flow3d", config)
    rebuilt.load_state_dict(old.state_dict(), strict=True)
    assert rebuilt.refine_radius == (2, 1, 2) and rebuilt.cost_channels == 0 and rebuilt.refine_aggregate == (0, 0, 0)


def _box_mean_loop(cost: torch.Tensor, half_widths: tuple[int, int, int]) -> torch.Tensor:
    """Slow reference: every voxel's mean over the voxels of its ±(ax, ay, az) box that lie in the grid."""
    ax, ay, az = half_widths
    _, _, Z, Y, X = cost.shape
    out = torch.empty_like(cost)
    for z in range(Z):
        for y in range(Y):
            for x in range(X):
                box = cost[:, :, max(0, z - az):z + az + 1, max(0, y - ay):y + ay + 1, max(0, x - ax):x + ax + 1]
                out[:, :, z, y, x] = box.mean(dim=(2, 3, 4))
    return out


@pytest.mark.parametrize("half_widths", [(1, 1, 1), (2, 0, 1), (0, 0, 0)])
def test_aggregate_costs_is_the_clipped_box_mean(half_widths):
    from core.models.flow3d import aggregate_costs

    torch.manual_seed(1)
    cost = torch.randn(2, 5, 4, 3, 6)
    torch.testing.assert_close(aggregate_costs(cost, half_widths), _box_mean_loop(cost, half_widths))


@pytest.mark.parametrize("half_widths", [(1, 1, 1), (2, 0, 1), (7, 1, 0)])
def test_aggregate_costs_gradient_is_the_loops(half_widths):
    """The hand-written backward against autograd through the slow loop (7: a box wider than the axis)."""
    from core.models.flow3d import aggregate_costs

    g = torch.Generator().manual_seed(4)
    cost = torch.randn(2, 3, 4, 3, 5, generator=g, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(2, 3, 4, 3, 5, generator=g, dtype=torch.float64)
    (fast,) = torch.autograd.grad((aggregate_costs(cost, half_widths) * weights).sum(), cost)
    (slow,) = torch.autograd.grad((_box_mean_loop(cost, half_widths) * weights).sum(), cost)
    torch.testing.assert_close(fast, slow)


def test_refine_aggregate_recovers_a_rigid_shift_single_voxels_miss():
    """A block shifted by (2, 0, 1) voxels in noise-corrupted features: the grid step's box-aggregated costs
    find the shift at the block's voxels where single-voxel costs are fooled by the noise more often."""
    torch.manual_seed(0)
    Z, Y, X, C = 12, 4, 12, 4
    f0 = torch.randn(1, C, Z, Y, X)
    f1 = torch.randn(1, C, Z, Y, X)
    f1[:, :, 4:10, :, 5:11] = f0[:, :, 3:9, :, 3:9]  # block content at (x 3..8, z 3..8) moves by dx 2, dz 1
    noisy0 = f0 + 1.2 * torch.randn_like(f0)

    def block_error(aggregate):
        net = Flow3D(in_channels=C, channels=C, levels=1, hidden=4, radius=(0, 0, 0), refine_radius=(2, 0, 2),
                     unit_cost=True, refine=True, inputs="volume", beta=200.0,
                     zero_bias=0.0, refine_aggregate=aggregate)
        with torch.no_grad():  # identity pyramid features: compare the inputs themselves
            for conv in (net.features[0], net.features[2]):
                conv.weight.zero_(); conv.bias.zero_()
            for c in range(C):
                net.features[0].weight[c, c, 1, 1, 1] = 1.0
                net.features[2].weight[c, c, 1, 1, 1] = 1.0
            flow = net(noisy0, f1)["flow"][0]  # 3×Z×Y×X
        true = torch.tensor([2.0, 0.0, 1.0]).view(3, 1, 1)
        inner = flow[:, 4:8, :, 4:8]  # block voxels away from its edges: 3×4×Y×4
        return (inner - true.view(3, 1, 1, 1)).abs().sum(0).mean()

    single, boxed = block_error((0, 0, 0)), block_error((1, 1, 1))
    assert boxed < 0.5 * single and boxed < 0.3
    assert Flow3D(in_channels=4, inputs="volume", refine_aggregate=(1, 0, 1)).config()["refine_aggregate"] == [1, 0, 1]
    with pytest.raises(ValueError, match="refine_aggregate"):
        Flow3D(in_channels=4, inputs="volume", refine_aggregate=(1, -1, 1))
