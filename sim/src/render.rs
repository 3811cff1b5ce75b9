//! Offscreen rendering of the rig's five cameras (MuJoCo's OpenGL renderer on EGL; Mesa's
//! llvmpipe on a machine without a GPU). The renderer is `!Send`: the thread that owns the
//! [`crate::Sim`] renders too.

use crate::rig::CAMERAS;
use mujoco_rs::prelude::*;
use mujoco_rs::renderer::MjRenderer;
use std::sync::Arc;

/// Which meshes the cameras see. The FR3 and 2F-85 visual meshes have ~300k triangles and cost
/// most of a frame on a CPU renderer; their collision meshes look coarser and render ~3x faster.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Meshes {
    /// The detailed visual meshes (snapshots, people looking at the rig).
    Visual,
    /// Collision meshes instead of visual ones (the bridge's default: five cameras in real time).
    #[default]
    Collision,
}

impl std::str::FromStr for Meshes {
    type Err = UnknownMeshes;
    fn from_str(s: &str) -> Result<Meshes, UnknownMeshes> {
        match s {
            "visual" => Ok(Meshes::Visual),
            "collision" => Ok(Meshes::Collision),
            other => Err(UnknownMeshes(other.to_owned())),
        }
    }
}

impl std::fmt::Display for Meshes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Meshes::Visual => "visual",
            Meshes::Collision => "collision",
        })
    }
}

/// A `--meshes` value that is neither `visual` nor `collision`.
#[derive(Debug, Clone, thiserror::Error)]
#[error("unknown meshes `{0}` (expected visual or collision)")]
pub struct UnknownMeshes(pub String);

/// One rendered frame per camera, RGB8, row-major, top row first.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RenderedFrame {
    pub camera: &'static str,
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error(
        "cannot open an offscreen OpenGL context ({0}); the sim renders through EGL on Mesa: \
         `bash scripts/setup.sh` installs libegl1 libegl-mesa0 libgl1-mesa-dri"
    )]
    Context(String),
    #[error("rendering camera `{camera}` failed: {message}")]
    Render { camera: &'static str, message: String },
    #[error("the rig model has no camera `{0}`")]
    NoCamera(&'static str),
}

/// The five cameras' renderer.
pub struct Cameras {
    renderer: MjRenderer,
    ids: Vec<(&'static str, usize)>,
    width: usize,
    height: usize,
}

impl std::fmt::Debug for Cameras {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Cameras").field("width", &self.width).field("height", &self.height).finish()
    }
}

impl Cameras {
    pub fn new(model: &MjModel, width: usize, height: usize, meshes: Meshes) -> Result<Cameras, RenderError> {
        let mut renderer = MjRenderer::builder()
            .width(width as u32)
            .height(height as u32)
            .rgb(true)
            .depth(false)
            .build(model)
            .map_err(|e| RenderError::Context(e.to_string()))?;
        if meshes == Meshes::Collision {
            // Group 2 holds the Menagerie models' visual geoms, group 3 their collision geoms.
            let opts = renderer.opts_mut();
            opts.geomgroup[2] = 0;
            opts.geomgroup[3] = 1;
            // The 2F-85's collision geoms are its full visual meshes (~70k triangles): draw
            // their convex hulls (MuJoCo computes them for collision anyway).
            opts.flags[mujoco_rs::mujoco_c::mjtVisFlag::mjVIS_CONVEXHULL as usize] = 1;
        }
        let ids = camera_ids(model)?;
        Ok(Cameras { renderer, ids, width, height })
    }

    /// These cameras pointed at `model`, a scene rebuilt from `old`'s rig: the OpenGL context
    /// (an EGL display, context and surface on Mesa) is kept rather than opened anew for every
    /// scene. The scene's textures (drawn per seed) are uploaded again, its meshes when they
    /// differ from `old`'s; a model whose assets differ in number or size gets a new MuJoCo
    /// rendering context for itself at the next render, still in the same OpenGL context.
    pub fn retarget(&mut self, old: &MjModel, model: &MjModel) -> Result<(), RenderError> {
        self.ids = camera_ids(model)?;
        if model.is_asset_compatible_with_model(old) {
            let fail = |e: mujoco_rs::renderer::RendererError| RenderError::Context(e.to_string());
            self.renderer.update_textures_from(model).map_err(fail)?;
            let same_meshes = old.mesh_vert() == model.mesh_vert()
                && old.mesh_face() == model.mesh_face()
                && old.mesh_normal() == model.mesh_normal();
            if !same_meshes {
                self.renderer.update_meshes_from(model).map_err(fail)?;
            }
            if model.nhfield() > 0 {
                self.renderer.update_hfields_from(model).map_err(fail)?;
            }
        }
        Ok(())
    }

    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Renders `camera` (one of [`CAMERAS`]) for the current state of `data` into `out`.
    pub fn render_into(
        &mut self,
        data: &mut MjData<Arc<MjModel>>,
        camera: &'static str,
        out: &mut Vec<u8>,
    ) -> Result<(), RenderError> {
        let &(name, id) = self.ids.iter().find(|(n, _)| *n == camera).ok_or(RenderError::NoCamera(camera))?;
        let fail = |e: mujoco_rs::renderer::RendererError| RenderError::Render { camera: name, message: e.to_string() };
        self.renderer.set_camera(MjvCamera::new_fixed(id));
        self.renderer.sync_data(data).map_err(fail)?;
        self.renderer.render().map_err(fail)?;
        let rgb = self.renderer.rgb_flat().ok_or(RenderError::Render { camera: name, message: "no RGB".into() })?;
        out.clear();
        out.extend_from_slice(rgb);
        Ok(())
    }

    /// Renders every camera, in [`CAMERAS`] order.
    pub fn render_all(&mut self, data: &mut MjData<Arc<MjModel>>) -> Result<Vec<RenderedFrame>, RenderError> {
        let mut frames = Vec::with_capacity(CAMERAS.len());
        for camera in CAMERAS {
            let mut rgb = Vec::with_capacity(self.width * self.height * 3);
            self.render_into(data, camera, &mut rgb)?;
            frames.push(RenderedFrame { camera, width: self.width, height: self.height, rgb });
        }
        Ok(frames)
    }
}

/// The five cameras' ids in `model`.
fn camera_ids(model: &MjModel) -> Result<Vec<(&'static str, usize)>, RenderError> {
    CAMERAS
        .iter()
        .map(|&name| {
            model.name_to_id(MjtObjBase::mjOBJ_CAMERA, name).map(|id| (name, id)).ok_or(RenderError::NoCamera(name))
        })
        .collect()
}
