"""Whether ISA-L's igzip (the shard writer's RGB compressor) gives this machine the bytes it
gives the 2-core development machine: igzip picks its code by CPU features, and its output is
reported equal on CPUs with SSE4.2, AVX and AVX2 and different without SSE4.2; AVX-512 hosts
(such as the lent GPU machines) had not been checked. Run by bench/gpu_check.sh's env step.

Compresses fixed images (a smooth gradient, the same with hashed noise, that image with flat
square "drops") at the writer's level and prints each stream's sha256 and whether it matches
the development machine's; exit status 0 either way (a measurement, not a test).

    python bench/deflate_identity.py [--json OUT]
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import numpy as np
from isal import isal_zlib

from rainbench.store.shard import RGB_DEFLATE_LEVEL, _deflate

EXPECTED = {
    "gradient": "f6d180ec1ce2491f07c197ceb9000b232a739c865388c4d61269f06b7904516b",
    "noisy": "ca8ba750b345b737a161d7cf8b29f92f1ecfe85613cda61f9e17a55453068276",
    "drops": "c7d58128c9525025773955a4e99b330c62fcdfcd3db4ebc6661638297e2a9ecd",
}
"""sha256 of each image's stream on the 2-core development machine (AVX2, no AVX-512)."""


def images() -> dict[str, np.ndarray]:
    """(600, 800, 3) uint8 test images, the same on every machine (integer arithmetic only)."""
    rows = np.arange(600, dtype=np.int64)[:, None, None]
    cols = np.arange(800, dtype=np.int64)[None, :, None]
    channel = np.arange(3, dtype=np.int64)[None, None, :]
    gradient = ((rows * 3 + cols * 2 + channel * 50) // 7 % 256).astype(np.uint8)
    # noise from an integer hash of the pixel index (no random generator, whose stream may
    # change between NumPy versions)
    index = np.arange(600 * 800 * 3, dtype=np.uint64).reshape(600, 800, 3)
    noise = ((index * np.uint64(2654435761) + np.uint64(12345)) >> np.uint64(16)) % np.uint64(24)
    noise = noise.astype(np.uint8)
    noisy = (gradient // 2 + noise).astype(np.uint8)
    drops = noisy.copy()
    for drop in range(40):  # square "drops" of a flat colour
        top, left = (drop * 97) % 560, (drop * 193) % 760
        drops[top:top + 40, left:left + 40] = (drop * 37) % 256
    return {"gradient": gradient, "noisy": noisy, "drops": drops}


def cpu_flags() -> list[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return []
    flags = next((line.split(":", 1)[1].split() for line in text.splitlines()
                  if line.startswith("flags")), [])
    return [flag for flag in ("sse4_2", "avx", "avx2", "avx512f", "avx512bw") if flag in flags]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    result = {"level": RGB_DEFLATE_LEVEL, "cpu_flags": cpu_flags(), "images": {}}
    for name, image in images().items():
        stream = _deflate(image)
        if isal_zlib.decompress(stream) != image.tobytes():
            raise SystemExit(f"{name}: the stream does not inflate to the image")
        digest = hashlib.sha256(stream).hexdigest()
        same = EXPECTED.get(name) == digest if EXPECTED else None
        result["images"][name] = {"bytes": len(stream), "sha256": digest, "same_as_dev": same}
        print(f"{name}: {len(stream)} bytes, sha256 {digest[:16]}, same as the development "
              f"machine: {same}")
    print("cpu flags:", " ".join(result["cpu_flags"]))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
