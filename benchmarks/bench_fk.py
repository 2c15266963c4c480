"""Forward kinematics of the bundled upper body (19 links, 24 DOFs) for 1, 1000, 100000 poses.

jaxmocap ``jit(vmap(fk))`` (and ``jit(fk)`` for one pose) vs pytorch-kinematics'
``forward_kinematics_tensor`` (torch, CPU) vs a batched NumPy implementation of the same
3x3-rotation + translation recursion (the plain baseline). float32 (the user default); all
three are checked to agree before timing. The stereo particle filter needs N = 1000 poses per
frame (Azad et al. 2007 §V: 23 ms for FK + projection at N = 1000), the pose database 10^5.
Run: python benchmarks/bench_fk.py
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytorch_kinematics as pk
import torch

from benchmarks._common import Row, sized, time_call, time_compile, write_results
from jaxmocap.body import FIXED, PRISMATIC, REVOLUTE, default_body, fk
from jaxmocap.body.model import DEFAULT_URDF
from jaxmocap.body.urdf import prepare_urdf, read_urdf_text


def numpy_fk(chain, q: np.ndarray) -> np.ndarray:
    """Batched NumPy FK (B, n_links, 4, 4): the same recursion, vectorised over poses."""
    b, dt = q.shape[0], q.dtype
    origin = np.asarray(chain.joint_origin, dt)
    axis = np.asarray(chain.joint_axis, dt)
    w = q[:, 3:6]
    th = np.linalg.norm(w, axis=1, keepdims=True)
    k = w / np.maximum(th, 1e-12)

    def rodrigues(k, th):  # (B, 3), (B, 1) -> (B, 3, 3)
        kx = np.zeros((k.shape[0], 3, 3), dt)
        kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
        kx -= kx.transpose(0, 2, 1)
        s, c = np.sin(th)[:, :, None], np.cos(th)[:, :, None]
        return np.eye(3, dtype=dt) + s * kx + (1 - c) * (kx @ kx)

    rots, trans = [], []
    for i, (p, t, d) in enumerate(chain.topology):
        r_loc = np.broadcast_to(origin[i, :3, :3], (b, 3, 3))
        t_loc = np.broadcast_to(origin[i, :3, 3], (b, 3))
        if t == REVOLUTE:
            r_loc = r_loc @ rodrigues(np.broadcast_to(axis[i], (b, 3)), q[:, d : d + 1])
        elif t == PRISMATIC:
            t_loc = t_loc + (origin[i, :3, :3] @ axis[i])[None] * q[:, d : d + 1]
        else:
            assert t == FIXED
        if p < 0:
            r_root = rodrigues(k, th)
            rots.append(r_root @ r_loc)
            trans.append(np.einsum("bij,bj->bi", r_root, t_loc) + q[:, :3])
        else:
            rots.append(rots[p] @ r_loc)
            trans.append(np.einsum("bij,bj->bi", rots[p], t_loc) + trans[p])
    out = np.zeros((b, len(rots), 4, 4), dt)
    out[:, :, :3, :3] = np.stack(rots, 1)
    out[:, :, :3, 3] = np.stack(trans, 1)
    out[:, :, 3, 3] = 1
    return out


def main() -> None:
    model = default_body()
    chain = model.chain
    pk_chain = pk.build_chain_from_urdf(prepare_urdf(read_urdf_text(DEFAULT_URDF))[1])
    order = pk_chain.get_frame_indices(*chain.link_names).numpy()  # pk frames in our order
    rng = np.random.default_rng(0)
    fk_v = jax.jit(jax.vmap(fk, in_axes=(None, 0)))
    fk_1 = jax.jit(fk)
    rows, summary = [], ["float32; CPU shared with other jobs (numbers are noisy, ratios matter)"]
    for n in sized(full=(1, 1000, 100_000), quick=(1, 1000)):
        lo, hi = np.asarray(chain.lower[6:]), np.asarray(chain.upper[6:])
        q = np.concatenate(
            [np.zeros((n, 6)), rng.uniform(lo, hi, size=(n, lo.shape[0]))], axis=1
        ).astype(np.float32)
        qj, qt = jnp.asarray(q), torch.from_numpy(q[:, 6:])
        ours = np.asarray(fk_v(chain, qj))
        ref_np = numpy_fk(chain, q)
        with torch.no_grad():
            ref_pk = pk_chain.forward_kinematics_tensor(qt).numpy()[order].transpose(1, 0, 2, 3)
        np.testing.assert_allclose(ours, ref_np, atol=1e-5)
        np.testing.assert_allclose(ours, ref_pk, atol=1e-5)
        reps = 5 if n == 100_000 else 50
        kernel = f"fk {n} poses"
        comp = time_compile(lambda qj=qj: jax.jit(jax.vmap(fk, in_axes=(None, 0)))(chain, qj))
        med, mn = time_call(lambda qj=qj: fk_v(chain, qj), n=reps)
        rows.append(Row(kernel, "jaxmocap jit(vmap(fk))", med, mn, reps, comp))
        jax_ms = med
        if n == 1:
            comp1 = time_compile(lambda q0=qj[0]: jax.jit(fk)(chain, q0))
            med, mn = time_call(lambda q0=qj[0]: fk_1(chain, q0), n=reps)
            rows.append(Row(kernel, "jaxmocap jit(fk)", med, mn, reps, comp1))
            jax_ms = min(jax_ms, med)

        def run_pk(qt=qt):
            with torch.no_grad():
                return pk_chain.forward_kinematics_tensor(qt)

        med_pk, mn = time_call(run_pk, n=reps)
        rows.append(Row(kernel, "pytorch-kinematics fk_tensor", med_pk, mn, reps))
        med_np, mn = time_call(lambda q=q: numpy_fk(chain, q), n=reps)
        rows.append(Row(kernel, "NumPy batched", med_np, mn, reps))
        summary.append(
            f"{n} poses: jaxmocap {jax_ms:.3f} ms, {med_pk / jax_ms:.1f}x faster than "
            f"pytorch-kinematics ({med_pk:.3f} ms), {med_np / jax_ms:.1f}x faster than NumPy "
            f"({med_np:.3f} ms)"
        )
    path = write_results("bench_fk", rows, summary)
    print("\n".join(summary))
    print(path.read_text())


if __name__ == "__main__":
    main()
