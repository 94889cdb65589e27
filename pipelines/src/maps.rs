//! What one frame of the stereo graph made, read back as whole maps: the whole-frame
//! matcher's (`reconstruct`) and the cells-only graph's (`reconstruct --cells`).

use crate::Error;
use crate::stereo::{Stereo, got};
use runtime::exec::Frame;
use schemas::{
    CellLists, Cloud, Disparity, DisparityMap, DisparityTiles, Image, Labels, Mask, Plane, Targets,
};

/// A whole-frame run's maps.
pub struct PairMaps {
    /// The left-based map after the LR check, as tiles (its validation figures).
    pub checked: DisparityTiles,
    /// The left-based map after the LR check.
    pub raw: DisparityMap,
    /// The right-based map after the LR check.
    pub raw_right: DisparityMap,
    /// The post-processed map.
    pub disparity: DisparityMap,
    /// The points and the cells in 3D, where the graph triangulates.
    pub cloud: Option<(Cloud, Targets)>,
}

/// A cells-only run's maps and cells.
pub struct CellMaps {
    /// Both views' labels.
    pub labels: Labels,
    /// Both views' cells.
    pub lists: CellLists,
    /// The LR-checked cell tiles.
    pub tiles: DisparityTiles,
    /// The cells in 3D and the substrate.
    pub targets: Targets,
    /// The points.
    pub cloud: Cloud,
    /// The final map in frame coordinates.
    pub disparity: Disparity,
    /// The LR-checked map and its occlusions on the same pixels, composed from the tiles.
    pub composed: cells::Composed,
    /// The left view in colour.
    pub colour: Image,
}

impl Stereo {
    /// The maps of a whole-frame run's frame `f`.
    pub fn pair_maps(&self, f: &Frame) -> Result<PairMaps, Error> {
        let outs = self.outs();
        let checked = f.read(&outs.checked).map_err(Error::Node)?;
        let raw_right = f.read(&outs.checked_right).map_err(Error::Node)?.paste();
        let disparity = got(f, &outs.post)?.paste();
        let cloud = match self.geometry {
            Some(_) => Some((got(f, &outs.cloud)?, got(f, &outs.targets)?)),
            None => None,
        };
        Ok(PairMaps {
            raw: checked.paste(),
            checked,
            raw_right,
            disparity,
            cloud,
        })
    }

    /// The left view's local-variance histogram and the segmentation's threshold on frame
    /// `f` (`None` without segmentation), for the report's figure: segmented again, as the
    /// segment node does, since its output holds cells, not the histogram.
    pub fn variance_histogram(&self, f: &Frame) -> Option<([u64; 256], u16)> {
        let params = self.segment.as_ref()?;
        let frame = f.read(&self.outs().frame).ok()?;
        let seg = segment::segment(&frame.left, params);
        Some((seg.histogram, seg.threshold))
    }

    /// The maps and cells of a cells-only run's frame `f`.
    pub fn cell_maps(&self, f: &Frame) -> Result<CellMaps, Error> {
        let outs = self.outs();
        let labels = got(f, &outs.labels)?;
        let lists = got(f, &outs.cells)?;
        let tiles = f.read(&outs.checked).map_err(Error::Node)?;
        let post = got(f, &outs.post)?;
        let composed = cells::compose(
            (&labels.left, &cells::mask_of(&labels.left)),
            (&lists.left, &lists.right),
            &post,
            &tiles,
        )
        .map_err(Error::Node)?;
        Ok(CellMaps {
            targets: got(f, &outs.targets)?,
            cloud: got(f, &outs.cloud)?,
            disparity: got(f, &outs.disparity)?,
            colour: f.read(&outs.colour).map_err(Error::Node)?,
            labels,
            lists,
            tiles,
            composed,
        })
    }
}

/// 255 where `map` has no disparity (an occlusion or a mismatch the LR check refused).
pub fn occlusion(map: &DisparityMap) -> Mask {
    Plane::from_vec(
        map.width,
        map.height,
        map.data
            .iter()
            .map(|d| if d.is_finite() { 0 } else { 255 })
            .collect(),
    )
    .expect("size")
}
