"""MAML-TRPO's conjugate gradient on point_nav with the KL's curvature products computed by
reverse-over-reverse differentiation (the library's
:func:`~armeta_rl.rl.trpo.meta_kl_hessian_vector_product`) and by forward mode, in CPU time.

At θ = θ_old the Hessian of the weighted KL is exactly Σ_k J_kᵀ J_out,kᵀ F J_out,k J_k (the
generalized Gauss–Newton form, Schraudolph 2002; Martens 2014, "New insights and perspectives on
the natural gradient method": it is the Hessian wherever the KL's gradient in the outputs
vanishes, as it does at its minimum), with J_k = I − α∇²L^in_k the inner step's
Jacobian (symmetric), J_out,k that of the adapted policy's (loc, scale) and F the Gaussian KL's
curvature in (loc, scale): w_k·m/(E·n_e)·(1/σ², 2/σ²) per step (m the step's mask, n_e the
episode's length). The library applies J_k and J_out,k by differentiating retained backward graphs
again; the forward-mode forms apply them as Jacobian-vector products of ``torch.func``
(forward-over-reverse through the inner gradient), J_kᵀ = J_k by symmetry, and J_out,kᵀ as one
vector-Jacobian product:

* ``forward mode``: ``torch.func.jvp`` in every product (each recomputes the primal pass);
* ``forward mode, linearized``: ``torch.func.linearize`` of the inner step once per solve (its
  trace counted in the solve), then tangents only;
* ``forward mode, compiled``: the whole forward-mode product through ``torch.compile`` (its
  compile, subprocesses included, reported apart; ``--no-compile`` skips it).

Each round collects a fresh point_nav batch at the current θ (20 tasks × 20 episodes × 100
steps), times one full meta-iteration of the library and then one conjugate-gradient solve (10
products, ``trust_region_step``) by each form in a rotating order, in this process's CPU time
(``os.times``, children included). It reports the median over the rounds and the largest
deviation of each form's product and step direction from the library's, relative to the largest
entry of the library's. Prints the table and writes it to its section of docs/benchmarks.md and
of docs/speed-options.md; run ``OMP_NUM_THREADS=1 python benchmarks/bench_curvature.py``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable
from functools import partial

import torch
from timing import DOCS, as_trained, markdown_table, trainer_for, write_section
from torch import Tensor
from torch.func import grad, jvp, linearize, vjp

from armeta_rl.learners.maml_trpo import MAMLTRPOLeader, MetaBatch, Params
from armeta_rl.rl.baseline import episode_mean
from armeta_rl.rl.policy import loc_scale, log_prob
from armeta_rl.rl.trpo import flatten, trust_region_step

Product = Callable[[Tensor], Tensor]
EPSILON = torch.finfo(torch.float32).eps
"""Relative size of the noise put on the library's products to show how far float32 rounding
alone moves conjugate gradient's step."""


def cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (inductor compiles in workers)."""
    times = os.times()
    return times.user + times.system + times.children_user + times.children_system


def perturbed(product: Product, generator: torch.Generator) -> Product:
    """``product`` with each result multiplied entrywise by (1 + ε·N(0, 1)), ε = float32's
    machine epsilon: a product exact up to rounding."""
    def noisy(vector: Tensor) -> Tensor:
        exact = product(vector)
        return exact * (1 + EPSILON * torch.randn(exact.shape, generator=generator))

    return noisy


def gaussian_kl_curvature(
    loc_tangent: Tensor, scale_tangent: Tensor, scale: Tensor, weights: Tensor, mask: Tensor
) -> tuple[Tensor, Tensor]:
    """F·(loc, scale) tangents: the Hessian of Σ_k w_k episode_mean(KL(N(μ, σ) ‖ N(μ₀, σ₀))) in
    (μ, σ) at μ = μ₀, σ = σ₀, diagonal with w_k·m/(E·n_e)·1/σ² (loc) and ·2/σ² (scale)."""
    steps = mask.to(scale.dtype)
    coefficient = steps / steps.sum(-1, keepdim=True).clamp_min(1.0) / mask.shape[1]
    coefficient = (weights[:, None, None] * coefficient)[..., None] / scale.square()
    return coefficient * loc_tangent, 2.0 * coefficient * scale_tangent


def forward_mode_pieces(leader: MAMLTRPOLeader, batch: MetaBatch):
    """The inner step θ_b ↦ θ'(θ_b) as a pure function, its point θ_b, and the adapted policies'
    outputs with their vector-Jacobian product."""
    net, lr = leader.net, leader.inner_lr
    train, advantages = batch.train, batch.train_advantages
    theta = {name: value.detach().clone() for name, value in batch.broadcast.items()}

    def inner_loss(params: Params) -> Tensor:
        loc, scale = loc_scale(net, params, train["observation"])
        return -episode_mean(log_prob(loc, scale, train["action"]) * advantages,
                             train["mask"]).sum()

    def adapt(params: Params) -> Params:
        gradient = grad(inner_loss)(params)
        return {name: params[name] - lr * gradient[name] for name in params}

    def outputs(adapted: Params) -> tuple[Tensor, Tensor]:
        return loc_scale(net, adapted, batch.valid["observation"])

    adapted = {name: value.detach() for name, value in batch.adapted.items()}
    (loc, scale), pullback = vjp(outputs, adapted)
    return adapt, theta, adapted, outputs, scale, pullback


def forward_mode_product(
    leader: MAMLTRPOLeader, batch: MetaBatch, weights: Tensor, linearized: bool
) -> Product:
    """v ↦ (Σ_k J_k J_out,kᵀ F J_out,k J_k + damping·I) v by Jacobian-vector products."""
    adapt, theta, adapted, outputs, scale, pullback = forward_mode_pieces(leader, batch)
    mask, damping = batch.valid["mask"], leader.cg_damping
    if linearized:
        _, inner_tangent = linearize(adapt, theta)
    else:
        def inner_tangent(tangent: Params) -> Params:
            return jvp(adapt, (theta,), (tangent,))[1]

    def product(vector: Tensor) -> Tensor:
        pieces = dict(zip(theta, torch.split(vector, [p[0].numel() for p in theta.values()])))
        tangent = {name: pieces[name].view(p.shape[1:]).expand_as(p) for name, p in theta.items()}
        _, (loc_t, scale_t) = jvp(outputs, (adapted,), (inner_tangent(tangent),))
        (back,) = pullback(gaussian_kl_curvature(loc_t, scale_t, scale, weights, mask))
        inner_back = inner_tangent(back)
        return flatten([inner_back[name].sum(0) for name in theta]) + damping * vector

    return product


def compiled_product(leader: MAMLTRPOLeader) -> Callable[..., Tensor]:
    """The forward-mode product as one compiled pure function of the batch's tensors."""
    net, lr, damping = leader.net, leader.inner_lr, leader.cg_damping

    def product(theta: Params, obs: Tensor, action: Tensor, mask: Tensor, advantages: Tensor,
                valid_obs: Tensor, valid_mask: Tensor, weights: Tensor, vector: Tensor) -> Tensor:
        def inner_loss(params: Params) -> Tensor:
            loc, scale = loc_scale(net, params, obs)
            return -episode_mean(log_prob(loc, scale, action) * advantages, mask).sum()

        def adapt(params: Params) -> Params:
            gradient = grad(inner_loss)(params)
            return {name: params[name] - lr * gradient[name] for name in params}

        def outputs(adapted: Params) -> tuple[Tensor, Tensor]:
            return loc_scale(net, adapted, valid_obs)

        pieces = dict(zip(theta, torch.split(vector, [p[0].numel() for p in theta.values()])))
        tangent = {name: pieces[name].view(p.shape[1:]).expand_as(p) for name, p in theta.items()}
        adapted, adapted_t = jvp(adapt, (theta,), (tangent,))
        (_, scale), pullback = vjp(outputs, adapted)
        _, (loc_t, scale_t) = jvp(outputs, (adapted,), (adapted_t,))
        (back,) = pullback(gaussian_kl_curvature(loc_t, scale_t, scale, weights, valid_mask))
        _, inner_back = jvp(adapt, (theta,), (back,))
        return flatten([inner_back[name].sum(0) for name in theta]) + damping * vector

    return torch.compile(product)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--no-compile", action="store_true", help="skip the compiled form")
    args = parser.parse_args()
    as_trained()
    trainer, _ = trainer_for("method=maml", "benchmark=point_nav")
    leader: MAMLTRPOLeader = trainer.leader
    for _ in range(2):
        trainer.train_iteration()
    compiled = None if args.no_compile else compiled_product(leader)
    compile_seconds = float("nan")
    names = ["double backward (library)", "forward mode", "forward mode, linearized"]
    names += [] if compiled is None else ["forward mode, compiled"]
    solves: dict[str, list[float]] = {name: [] for name in names}
    products: dict[str, list[float]] = {name: [] for name in names}
    product_error = dict.fromkeys(names, 0.0)
    step_error = dict.fromkeys(names, 0.0)
    iterations = []
    control_error = 0.0
    for round_ in range(args.rounds):
        start = cpu_seconds()
        trainer.train_iteration()
        iterations.append(cpu_seconds() - start)
        batch = leader.collect(trainer.principle.propose(trainer.meta_batch), create_graph=True)
        weights = torch.full((trainer.meta_batch,), 1.0 / trainer.meta_batch)
        _, gradient, graph = leader.surrogate_gradient(batch, weights)
        reference_product = leader.kl_hessian_product(batch, weights, graph)
        expected = reference_product(gradient)
        expected_step = trust_region_step(gradient, reference_product, leader.max_kl,
                                          leader.cg_iterations)
        rounded = perturbed(reference_product, torch.Generator().manual_seed(round_))
        control = trust_region_step(gradient, rounded, leader.max_kl, leader.cg_iterations)
        control_error = max(control_error, float(
            (control - expected_step).abs().max() / expected_step.abs().max()))
        theta = {name: value.detach().clone() for name, value in batch.broadcast.items()}
        tensors = (batch.train["observation"], batch.train["action"], batch.train["mask"],
                   batch.train_advantages, batch.valid["observation"], batch.valid["mask"],
                   weights)
        if compiled is not None and round_ == 0:
            start = cpu_seconds()
            compiled(theta, *tensors, gradient)
            compile_seconds = cpu_seconds() - start

        order = names[round_ % len(names):] + names[: round_ % len(names)]
        for name in order:
            start = cpu_seconds()
            if name == names[0]:
                product = leader.kl_hessian_product(batch, weights, graph)
            elif name == "forward mode, compiled":
                product = partial(compiled, theta, *tensors)
            else:
                product = forward_mode_product(leader, batch, weights,
                                               name.endswith("linearized"))
            step = trust_region_step(gradient, product, leader.max_kl, leader.cg_iterations)
            solves[name].append(cpu_seconds() - start)
            tick = time.process_time()
            value = product(gradient)
            products[name].append(time.process_time() - tick)
            scale = expected.abs().max()
            product_error[name] = max(product_error[name],
                                      float((value - expected).abs().max() / scale))
            step_error[name] = max(step_error[name], float(
                (step - expected_step).abs().max() / expected_step.abs().max()))
        print({name: round(1000 * times[-1]) for name, times in solves.items()}, flush=True)
    iteration = statistics.median(iterations)
    base = statistics.median(solves[names[0]])
    rows = []
    for name in names:
        cg = statistics.median(solves[name])
        rows.append((name, f"{1000 * statistics.median(products[name]):.0f}",
                     f"{1000 * cg:.0f}", f"{base / cg:.2f}",
                     f"{1000 * (iteration - base + cg):.0f}",
                     f"{product_error[name]:.1e}", f"{step_error[name]:.1e}"))
    body = (
        f"MAML-TRPO on point_nav (20 tasks × 20 episodes × 100 steps), CPU time of one thread "
        f"(process and children), medians over {args.rounds} rounds; each round times one "
        f"meta-iteration of the library ({1000 * iteration:.0f} ms median) and then one "
        f"conjugate-gradient solve (10 KL curvature products, `trust_region_step`) by each form, "
        f"in a rotating order, on a fresh batch. The iteration column is the library's "
        f"meta-iteration with its solve replaced by the row's; the deviations are the largest "
        f"over the rounds of |product − library's| and |step direction − library's|, relative "
        f"to the largest entry of the library's. For scale, the library's own solve with each "
        f"product multiplied entrywise by (1 + {EPSILON:.1e}·N(0, 1)) "
        f"deviates by up to {control_error:.1e} from the unperturbed one."
        + ("" if compiled is None else
           f" The compiled form's first call (its compile) took {compile_seconds:.0f} CPU s.")
        + "\n\n"
        + markdown_table(("curvature product", "one product ms", "CG solve ms",
                          "speed-up on CG", "meta-iteration ms", "product deviation",
                          "step deviation"), rows))
    print(body)
    title = "KL curvature by forward mode in MAML-TRPO's conjugate gradient (bench_curvature.py)"
    write_section("bench_curvature", title, body)
    write_section("bench_curvature", title, body, DOCS / "speed-options.md")


if __name__ == "__main__":
    main()
