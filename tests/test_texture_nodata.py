"""No-data in ground textures is what a file declares (GeoTIFF GDAL_NODATA, an alpha channel, an explicit colour),
never a colour: black open water stays ground."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image, TiffImagePlugin

from sim.textures import REAL_TEXTURES, TEXTURE_DIR, load_real_tile, load_tile, read_nodata_mask

H, W = 320, 480


def _tile(rng: np.random.Generator) -> np.ndarray:
    """RGB texture with a pure black lake in the middle and a black corner (rows 0-99, columns 0-159)."""
    rgb = rng.integers(20, 230, (H, W, 3), dtype=np.uint8)
    rgb[120:220, 200:330] = 0          # water, black in every band
    rgb[:100, :160] = 0                # outside the survey
    return rgb


def _save_tiff(path, rgb: np.ndarray, tags: dict[int, str]) -> None:
    info = TiffImagePlugin.ImageFileDirectory_v2()
    for tag, text in tags.items():
        info[tag] = text
        info.tagtype[tag] = 2          # TIFF ASCII
    Image.fromarray(rgb).save(path, tiffinfo=info)


def test_black_is_ground_unless_declared(tmp_path):
    rgb = _tile(np.random.default_rng(1))
    plain = tmp_path / "plain.tif"
    _save_tiff(plain, rgb, {})
    assert read_nodata_mask(plain) == (None, "")
    assert load_tile(plain).shape == (H, W, 3)                  # the lake and the corner are ground
    # an explicit colour: the corner and the lake are both black, so both go; the largest clean rectangle is left
    cut = load_tile(plain, nodata_bgr=(0, 0, 0))
    assert cut.shape[0] < H or cut.shape[1] < W
    assert not np.all(cut == 0, axis=2).any()


def test_gdal_nodata_tag(tmp_path):
    rgb = _tile(np.random.default_rng(2))
    rgb[120:220, 200:330] = (0, 0, 3)                           # water nearly black, not the declared value
    f = tmp_path / "tagged.tif"
    _save_tiff(f, rgb, {42113: "0"})
    mask, how = read_nodata_mask(f)
    assert how == "GDAL_NODATA 0" and mask is not None
    assert mask[:100, :160].all() and mask.sum() == 100 * 160
    cut = load_tile(f)
    assert not np.all(cut == 0, axis=2).any()
    # the dark water is kept: the tile is cut only next to the declared corner (16 px blocks and their rim)
    assert cut.shape[1] == W or cut.shape[0] == H


def test_alpha_channel_and_a_band_gdal_calls_something_else(tmp_path):
    rng = np.random.default_rng(3)
    rgb = _tile(rng)
    alpha = np.full((H, W), 255, np.uint8)
    alpha[:100, :160] = 0
    png = tmp_path / "alpha.png"
    Image.fromarray(np.dstack([rgb, alpha]), "RGBA").save(png)
    mask, how = read_nodata_mask(png)
    assert how == "alpha channel" and mask is not None and mask.sum() == 100 * 160
    # a 4-band TIFF whose fourth band GDAL calls "Undefined" (NAIP's near infrared) has no alpha
    nir = rng.integers(0, 255, (H, W), dtype=np.uint8)
    nir[:100, :160] = 0
    tif = tmp_path / "rgbn.tif"
    meta = ('<GDALMetadata><Item name="COLORINTERP" sample="3" role="colorinterp">Undefined</Item>'
            "</GDALMetadata>")
    _save_tiff(tif, np.dstack([rgb, nir]), {42112: meta})
    assert read_nodata_mask(tif) == (None, "")


def test_project_tiles_keep_their_dark_ground():
    # NAIP farmland/wetland: GDAL_NODATA 0 in every band matches no texel, so the whole 4.7 x 3.6 km tile is kept
    file, _, declared = REAL_TEXTURES["farmland"]
    mask, how = read_nodata_mask(TEXTURE_DIR / file, declared)
    assert how == "GDAL_NODATA 0" and mask is None
    tile, m_per_px = load_real_tile("farmland")
    assert tile.shape == (723, 934, 3) and m_per_px == 5.0
    # the OAM town tile's corner outside the survey is declared in the texture table (the file declares nothing)
    town, _ = load_real_tile("town_river")
    assert town.shape == (1216, 1920, 3)


@pytest.mark.parametrize("name", ["dry_grassland", "forest_road"])
def test_tiles_without_no_data_are_whole(name):
    file, _, declared = REAL_TEXTURES[name]
    assert declared is None and read_nodata_mask(TEXTURE_DIR / file) == (None, "")
