"""The digest of the networks behind a measurement: part of the key of every cached measurement made with them."""

from __future__ import annotations

import hashlib

from kdtrace.config import ReconstructionProfile


def networks_fingerprint(profile: ReconstructionProfile | None = None) -> str:
    """Digest of the source that defines, trains and runs the networks, and of their stored weights.

    Part of the key of every cached measurement made with the networks (the sweep's and the
    §6.4 pipeline's rows): a model trained or evaluated by other code, or retrained into the
    profile's model store by the same code, is another model, so those rows are measured again.

    Parameters
    ----------
    profile : ReconstructionProfile, optional
        Its ``model_store`` adds every stored ``best.pt`` (name and bytes) to the digest; None or
        a profile without a store: the source only.
    """
    from kdtrace.cache import source_fingerprint
    from reconstruction import _blend_kernels, blend, data, hdr, inference, loss, models, train

    digest = hashlib.sha256(source_fingerprint(models, loss, data, hdr, inference, blend, _blend_kernels,
                                               train).encode())
    store = None if profile is None else train.model_store_root(profile)
    if store is not None:
        for weights in sorted(store.glob("*/best.pt")):
            digest.update(weights.parent.name.encode() + b"\0" + hashlib.sha256(weights.read_bytes()).digest())
    return digest.hexdigest()
