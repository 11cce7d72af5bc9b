"""A share of COLMAP's feature extraction and matching, in a process of its own (run as a script
by ``colmap_consistency``: it imports pycolmap only, not torch or the package).

Two pycolmap matchers running side by side in one process do not give the same result twice (the
order of a pair's matches moves with the interleaving, and the verification's RANSAC with it),
while one per process does: so the second share runs here, the first in the caller. Each line on
standard input is a JSON job, answered on standard output by one line, "ok" or "error: ...";
COLMAP's own lines go to standard error (the caller's log)."""

import sys

if __name__ == "__main__":  # run as a script: its folder (the package's modules) is not a place to import from
    sys.path[:] = [p for p in sys.path if p not in ("", sys.path[0])]

import json


def reader_options(camera_params: str):
    """COLMAP's image reader for one PINHOLE camera with the given "fx,fy,cx,cy"."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = camera_params
    return reader


def extract(job: dict) -> None:
    import pycolmap

    reader = reader_options(job["camera_params"])
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = job["max_image_size"]
    extraction.num_threads = job["threads"]
    pycolmap.extract_features(job["database"], job["images"], image_names=job["names"],
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)  # fmt: skip


def match(job: dict) -> None:
    import pycolmap

    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = job["pairs"]
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = job["threads"]
    pycolmap.match_image_pairs(job["database"], matching_options=matching, pairing_options=pairing,
                               device=pycolmap.Device.cpu)  # fmt: skip


JOBS = {"extract": extract, "match": match}


def main() -> None:
    failed = None
    try:  # imported before the first job arrives: the caller is still writing the views
        import pycolmap  # noqa: F401
    except Exception as e:  # the answer to every job
        failed = e
    for line in sys.stdin:
        job = json.loads(line)
        try:
            if failed is not None:
                raise failed
            JOBS[job["job"]](job)
            answer = "ok"
        except Exception as e:  # reported to the caller, which raises it
            answer = f"error: {type(e).__name__}: {e}".replace("\n", " ")
        sys.stdout.write(answer + "\n")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
