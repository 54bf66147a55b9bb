"""HFF6DoF training loss (paper section 3.6)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def hff_loss(seg_logits: torch.Tensor | None, vec_pred: torch.Tensor, seg_gt: torch.Tensor | None,
             vec_gt: torch.Tensor, obj_mask: torch.Tensor, w_vec: float = 2.0, ignore_index: int = -100,
             return_parts: bool = False):
    """Cross-entropy on the segmentation + w_vec x L1 on the keypoint vector field.

    seg_logits: (B,C,H,W) or None (segmentation head off: the term is dropped);
    vec_pred, vec_gt: (B,3K,H,W); seg_gt: (B,H,W) int64 class ids (0 = background);
    obj_mask: (B,H,W) bool, the object pixels where the vector field is defined.
    The L1 term is the mean of |vec_pred - vec_gt| over object pixels and all 3K channels (0 when
    there is no object pixel). Returns the scalar loss, or (loss, {"seg": .., "vec": ..}) with
    ``return_parts`` (the parts detached).
    """
    if vec_pred.shape != vec_gt.shape:
        raise ValueError(f"vec_pred {tuple(vec_pred.shape)} and vec_gt {tuple(vec_gt.shape)} differ")
    m = obj_mask.to(vec_pred.dtype)[:, None]                        # (B,1,H,W)
    n = m.sum() * vec_pred.shape[1]
    l_vec = ((vec_pred - vec_gt).abs() * m).sum() / n.clamp_min(1.0)
    if seg_logits is not None:
        if seg_gt is None:
            raise ValueError("seg_gt is needed when seg_logits is given")
        l_seg = F.cross_entropy(seg_logits, seg_gt.long(), ignore_index=ignore_index)
    else:
        l_seg = vec_pred.new_zeros(())
    loss = l_seg + w_vec * l_vec
    if return_parts:
        return loss, {"seg": l_seg.detach(), "vec": l_vec.detach()}
    return loss
