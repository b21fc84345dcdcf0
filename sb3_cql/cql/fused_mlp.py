"""A ReLU MLP's forward and backward as one autograd node: the same function and gradients as SB3's ``nn.Sequential``,
with fewer passes over CQL's ``batch * (1 + 3 * n_actions)`` rows. Each hidden layer is one oneDNN ``linear + ReLU``
(``addmm`` and an in-place ReLU where this torch build lacks it), and the input's gradient is computed only if needed
(``benchmarks/cql_speed.py`` measures the step).
"""

from __future__ import annotations

import torch as th
from torch import nn


def _onednn_linear():
    """oneDNN's fused ``linear + activation`` (the op Inductor uses on CPU), where this torch build has it."""
    try:
        return th.ops.mkldnn._linear_pointwise if th.backends.mkldnn.is_available() else None
    except (AttributeError, RuntimeError):
        return None


_ONEDNN_LINEAR = _onednn_linear()


class _ReluMlpFunction(th.autograd.Function):
    """``Linear -> ReLU -> ... -> Linear`` on ``(x, w1, b1, w2, b2, ...)`` with weights in ``nn.Linear``'s layout."""

    @staticmethod
    def forward(ctx, x: th.Tensor, *parameters: th.Tensor) -> th.Tensor:  # type: ignore[override]
        weights, biases = parameters[0::2], parameters[1::2]
        inputs = [x]
        onednn = _ONEDNN_LINEAR if x.device.type == "cpu" else None  # oneDNN runs on CPU tensors only
        for index, (weight, bias) in enumerate(zip(weights, biases, strict=True)):
            hidden = index < len(weights) - 1
            if onednn is not None:  # bias and ReLU applied inside oneDNN's matrix product
                x = onednn(x, weight, bias, "relu" if hidden else "none", [None], "")
            else:
                x = th.addmm(bias, x, weight.t().contiguous())
                if hidden:
                    x.relu_()
            if hidden:
                inputs.append(x)
        ctx.save_for_backward(*inputs, *weights)
        ctx.n_layers = len(weights)
        return x

    @staticmethod
    def backward(ctx, grad_output: th.Tensor) -> tuple[th.Tensor | None, ...]:  # type: ignore[override]
        saved = ctx.saved_tensors
        inputs, weights = saved[: ctx.n_layers], saved[ctx.n_layers :]
        grads: list[th.Tensor | None] = [None] * (2 * ctx.n_layers)
        grad: th.Tensor | None = grad_output
        for index in reversed(range(ctx.n_layers)):
            assert grad is not None
            grads[2 * index] = grad.t() @ inputs[index]
            grads[2 * index + 1] = grad.sum(dim=0)
            if index > 0:
                # inputs[index] is the ReLU's output: its gradient passes where the output is positive.
                grad = th.ops.aten.threshold_backward(grad @ weights[index], inputs[index], 0)
            else:
                grad = grad @ weights[0] if ctx.needs_input_grad[0] else None
        return (grad, *grads)


def relu_mlp_parameters(network: nn.Module) -> list[th.Tensor] | None:
    """The ``[w1, b1, w2, b2, ...]`` of an ``nn.Sequential`` of ``Linear`` layers with ``ReLU`` between them (SB3's
    ``create_mlp`` with the default activation), or ``None`` for any other network."""
    if not isinstance(network, nn.Sequential) or len(network) == 0:
        return None
    layers = list(network)
    linears, activations = layers[0::2], layers[1::2]
    if len(linears) != len(activations) + 1:
        return None
    if not all(isinstance(layer, nn.Linear) and layer.bias is not None for layer in linears):
        return None
    if not all(type(layer) is nn.ReLU for layer in activations):
        return None
    return [tensor for layer in linears for tensor in (layer.weight, layer.bias)]


def relu_mlp(x: th.Tensor, parameters: list[th.Tensor]) -> th.Tensor:
    """The network of :func:`relu_mlp_parameters` applied to ``x`` (a 2-D tensor)."""
    return _ReluMlpFunction.apply(x, *parameters)
