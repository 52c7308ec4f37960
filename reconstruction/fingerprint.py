"""The digest of the code behind the networks: part of the key of every cached measurement made with them."""

from __future__ import annotations


def networks_fingerprint() -> str:
    """Digest of the source that defines, trains and runs the networks and their datasets.

    Part of the key of every cached measurement made with the networks (the sweep's and the
    §6.4 pipeline's rows): a model cached under the same profile but trained or evaluated by
    other code is another model, so those rows are measured again.
    """
    from kdtrace.cache import source_fingerprint
    from reconstruction import _blend_kernels, blend, data, hdr, inference, loss, models, train

    return source_fingerprint(models, loss, data, hdr, inference, blend, _blend_kernels, train)
