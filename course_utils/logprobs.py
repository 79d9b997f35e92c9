"""Token log-probabilities and entropies from hidden states, without keeping [tokens, vocab] logits.

A language model's last layer turns each hidden state h (576 numbers for SmolLM2) into one
logit per vocabulary entry (49,152). Training needs only two numbers per token from those
logits: log pi(o_t) = z[o_t] - logsumexp(z) and the entropy H = logsumexp(z) - sum_v p_v z_v.
The plain way (``model(...).logits``, then ``log_softmax``) builds several [tokens, vocab]
float tensors, 100+ MB each for one cpu-preset batch, and the element-wise passes over them
(and the fresh memory they need) cost more than the whole transformer in bf16
(benchmarks/RESULTS.md). ``output_layer_logprobs`` walks the tokens in chunks, keeps only the
two numbers per token, and recomputes a chunk's logits in the backward pass (one more
output-layer matmul) instead of storing them. The backward does hold the logits' gradient for
every token at once, in the matmul dtype (for bf16, half the bytes of one fp32 logits tensor),
so that dW is one [vocab, hidden] product rather than one per chunk. The same idea is
behind Liger-Kernel's fused linear cross-entropy and Apple's Cut Cross-Entropy.

The gradient, for upstream gradients g (of log pi) and k (of H) at one token:

    d log pi(o) / dz = onehot(o) - p            dH / dz = -p * (log p + H)
    dz = g * (onehot(o) - p) - k * p * (log p + H),  divided by the temperature,

then dh = dz W and dW = dz^T h. ``tests/test_logprobs.py`` checks values and both gradients
against the plain computation and ``torch.autograd.gradcheck``.
"""

from __future__ import annotations

import torch

# tokens per chunk of the forward: [512, 49_152] float32 is 100 MB. Wide chunks keep the
# output-layer products efficient: in fp32, chunks of 32 tokens made a cpu-preset forward +
# backward slower than full logits; in bf16 the size hardly mattered (benchmarks/RESULTS.md).
CHUNK_TOKENS = 512


class _OutputLayerLogprobs(torch.autograd.Function):
    @staticmethod
    def forward(ctx, hidden, weight, ids, inv_temperature: float, dtype: torch.dtype, chunk: int):
        ctx.set_materialize_grads(False)   # an unused output's gradient arrives as None, not zeros
        w = weight.to(dtype)
        n = hidden.shape[0]
        wide = torch.promote_types(dtype, torch.float32)   # float32, or float64 for float64 inputs
        logp = hidden.new_empty(n, dtype=wide)
        entropy = hidden.new_empty(n, dtype=wide)
        lse_all = hidden.new_empty(n, dtype=wide)
        for start in range(0, n, chunk):
            rows = slice(start, start + chunk)
            z = (hidden[rows].to(dtype) @ w.T).to(wide)
            if inv_temperature != 1.0:
                z.mul_(inv_temperature)
            lse = torch.logsumexp(z, -1)
            logp[rows] = z.gather(-1, ids[rows, None]).squeeze(-1) - lse
            z.sub_(lse[:, None])                       # z is now log p
            entropy[rows] = -(z.exp() * z).sum(-1)
            lse_all[rows] = lse
        # the cast weight is kept for the backward (for bf16, half the fp32 weight's size)
        ctx.save_for_backward(hidden, w, ids, lse_all, entropy)
        ctx.weight_dtype = weight.dtype
        ctx.inv_temperature, ctx.dtype, ctx.chunk = inv_temperature, dtype, chunk
        return logp, entropy

    @staticmethod
    def backward(ctx, grad_logp, grad_entropy):
        hidden, w, ids, lse_all, entropy = ctx.saved_tensors
        tau_inv, dtype, chunk = ctx.inv_temperature, ctx.dtype, ctx.chunk
        n = hidden.shape[0]
        # dz for every token, in the matmul dtype: two matmuls at the end give dh and dW (one
        # [vocab, hidden] product instead of one per chunk)
        dz_all = hidden.new_empty(n, w.shape[0], dtype=dtype)
        for start in range(0, n, chunk):
            rows = slice(start, start + chunk)
            z = (hidden[rows].to(dtype) @ w.T).to(lse_all.dtype)
            if tau_inv != 1.0:
                z.mul_(tau_inv)
            log_p = z.sub_(lse_all[rows, None])
            p = log_p.exp()
            dz = p * -grad_logp[rows, None] if grad_logp is not None else torch.zeros_like(p)
            if grad_logp is not None:
                dz.scatter_add_(-1, ids[rows, None], grad_logp[rows, None].to(dz.dtype))
            if grad_entropy is not None:
                dz.sub_(grad_entropy[rows, None] * p * (log_p + entropy[rows, None]))
            if tau_inv != 1.0:
                dz.mul_(tau_inv)
            dz_all[rows] = dz
        grad_hidden = (dz_all @ w).to(hidden.dtype) if ctx.needs_input_grad[0] else None
        # (h^T dz)^T rather than dz^T h: the product then reads both operands in memory order
        grad_weight = ((hidden.to(dtype).T @ dz_all).T.to(ctx.weight_dtype)
                       if ctx.needs_input_grad[1] else None)
        return grad_hidden, grad_weight, None, None, None, None


def output_layer_logprobs(hidden: torch.Tensor, weight: torch.Tensor, ids: torch.Tensor,
                          temperature: float = 1.0, chunk: int = CHUNK_TOKENS):
    """log pi(ids) and the entropy of the tempered distribution softmax(hidden @ weight.T / T),
    one value per row of ``hidden`` [n, H] (``weight`` is the output layer's [vocab, H]).

    Inside an autocast block the products run in its dtype (bf16 on a CPU with matrix units),
    everything after them in float32; outside one, in the hidden states' dtype."""
    device = hidden.device.type
    dtype = torch.get_autocast_dtype(device) if torch.is_autocast_enabled(device) else hidden.dtype
    return _OutputLayerLogprobs.apply(hidden, weight, ids, 1.0 / temperature, dtype, chunk)


def body_and_head(model):
    """(the transformer without its output layer, the output layer's weight), or None when the
    model's logits are not a plain bias-free linear map of the last hidden state (then the
    caller computes full logits)."""
    try:
        head, body = model.get_output_embeddings(), model.get_decoder()
    except (AttributeError, NotImplementedError, ValueError):
        return None
    config = getattr(model, "config", None)
    plain = (type(head) is torch.nn.Linear and head.bias is None and body is not None
             and body is not model
             and getattr(config, "final_logit_softcapping", None) is None
             and getattr(config, "logit_scale", None) in (None, 1.0))
    return (body, head.weight) if plain else None
