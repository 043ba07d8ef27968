"""WGS 84 rows in each track's local frame: east, north (m) in the tangent plane at the track's
first position (:mod:`torchsvs.datasets.geodesy`), the positions out of range or astray read as
missing (:func:`project_rows`, what :func:`~torchsvs.datasets.rows.parse_block` runs on latitude
and longitude)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from torchsvs.datasets import geodesy

#: Farthest a track may reach from its first position in the local frame (degrees of arc):
#: the tangent plane folds over at 90°.
MAX_ARC = 80.0


def project_rows(
    position: np.ndarray, code: np.ndarray, time: np.ndarray, track_ids: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of latitude, longitude (degrees)[, altitude (m)] ``position [R, 2|3]`` of tracks
    ``code [R]`` (numbering ``track_ids``; -1: none) at ``time [R]`` in each track's local frame:
    east, north (m) in the tangent plane at the track's first position in time
    (:func:`~torchsvs.datasets.geodesy.to_local`), the altitude as it is. Coordinates out of
    range are read as missing (``invalid``), and so is a lone row farther than :data:`MAX_ARC`
    from its track's first position between nearer ones (a stray report: null island, a
    longitude off by 180°); a track reaching that far over successive rows raises
    ``ValueError``, naming the row it leaves the frame at.

    Returns:
        The positions in the local frames ``[R, 2|3]`` (NaN where missing), each track's
        reference latitude and longitude ``[len(track_ids), 2]`` and the rows read as missing
        ``[R]``."""
    lat, lon = position[:, 0].copy(), position[:, 1].copy()
    with np.errstate(invalid="ignore"):
        invalid = (np.abs(lat) > 90.0) | (lon < -180.0) | (lon > 360.0)
    lat[invalid] = lon[invalid] = np.nan
    usable = np.flatnonzero((code >= 0) & np.isfinite(time) & np.isfinite(lat + lon))
    first = usable[np.lexsort((time[usable], code[usable]))]
    if len(first):
        first = first[np.r_[True, code[first][1:] != code[first][:-1]]]
    reference = np.full((len(track_ids), 2), np.nan)
    reference[code[first]] = np.stack([lat[first], lon[first]], axis=1)
    ref = reference[np.maximum(code, 0)]
    with np.errstate(invalid="ignore"):
        far = geodesy.arc_degrees(lat, lon, ref[:, 0], ref[:, 1]) > MAX_ARC
    if far.any():
        stray = _strays(far, code, time)
        if (far & ~stray).any():
            at = np.flatnonzero(far & ~stray)[0]
            raise ValueError(
                f"track {track_ids[code[at]]!r}: reaches more than {MAX_ARC:.0f}° of arc "
                f"(about {MAX_ARC * 111:.0f} km) from its first position, from the row at time "
                f"{float(time[at])!r} s on (latitude {float(lat[at])!r}, longitude "
                f"{float(lon[at])!r}); the local "
                "east-north frame of a track covers less: split the track into shorter ones, or "
                "drop those rows if they are bad reports (a lone one is read as missing)"
            )
        # a lone report that far among near ones is a stray (a glitch): read as missing
        invalid |= stray
        lat[stray] = lon[stray] = np.nan
    local = position.copy()
    with np.errstate(invalid="ignore"):
        local[:, :2] = geodesy.to_local(
            np.nan_to_num(lat),
            np.nan_to_num(lon),
            np.nan_to_num(ref[:, 0]),
            np.nan_to_num(ref[:, 1]),
        )
    local[~np.isfinite(lat + lon) | (code < 0), :2] = np.nan
    return local, reference, invalid


def _strays(far: np.ndarray, code: np.ndarray, time: np.ndarray) -> np.ndarray:
    """``[R]`` bool: the ``far`` rows whose track's previous and next rows in time are not far
    (rows without a track or a time are never)."""
    usable = np.flatnonzero((code >= 0) & np.isfinite(time))
    order = usable[np.lexsort((time[usable], code[usable]))]
    f, c = far[order], code[order]
    before = np.r_[False, f[:-1] & (c[:-1] == c[1:])]  # the previous row of the track is far
    after = np.r_[f[1:] & (c[1:] == c[:-1]), False]
    stray = np.zeros(len(far), dtype=bool)
    stray[order] = f & ~before & ~after
    return stray
