//! Embree 3 (Debian's `libembree-dev` 3.13.5, `-lembree3`) in process, for `emc compare`: a
//! minimal hand-written binding of the functions the peer harness uses ([`sys`]) and a safe
//! face over it ([`Device`], [`Mesh`], [`Scene`]) that sets Embree up exactly as
//! `../shared/peers/embree/embree_bench.c` does.
//!
//! Setup, as the harness: one device per thread count (`threads=N,verbose=0`) with an error
//! callback and a memory monitor; per build a fresh scene with `RTC_SCENE_FLAG_NONE` and the
//! same build quality on scene and geometry, one triangle geometry over *shared* buffers (the
//! vertex buffer padded by 16 bytes at the end, for Embree's 16-byte loads), attached and
//! released, then `rtcCommitScene`. Rays go one per `rtcIntersect1` / `rtcOccluded1` call with
//! an intersect context flagged COHERENT for primary rays and INCOHERENT for AO rays; a hit is
//! `geomID != RTC_INVALID_GEOMETRY_ID`, an occlusion `tfar < 0`.
//!
//! The nearest analogue of `Accel::rebuild` ("warm" builds): `rtcUpdateGeometryBuffer` on the
//! vertex buffer, `rtcCommitGeometry`, `rtcCommitScene` on the same scene.

use std::ffi::{c_char, c_void, CStr, CString};
use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use glam::Vec3;

use crate::peers::{trace_closest, trace_occluded, Timing, Tracer};
use crate::trace::{Hit, Ray};

/// The C declarations, transcribed from `/usr/include/embree3/*.h` of Embree 3.13.5
/// (`RTC_MAX_INSTANCE_LEVEL_COUNT` 1, `RTC_MIN_WIDTH` 0). `tests/compare.rs` checks every
/// struct's size, alignment and field offsets against the C compiler's view of the headers.
pub mod sys {
    use std::ffi::{c_char, c_uint, c_void};

    /// Opaque device (`struct RTCDeviceTy`).
    #[repr(C)]
    #[derive(Debug)]
    pub struct RTCDeviceTy {
        _opaque: [u8; 0],
    }
    /// Opaque scene (`struct RTCSceneTy`).
    #[repr(C)]
    #[derive(Debug)]
    pub struct RTCSceneTy {
        _opaque: [u8; 0],
    }
    /// Opaque geometry (`struct RTCGeometryTy`).
    #[repr(C)]
    #[derive(Debug)]
    pub struct RTCGeometryTy {
        _opaque: [u8; 0],
    }
    /// `RTCDevice`.
    pub type RTCDevice = *mut RTCDeviceTy;
    /// `RTCScene`.
    pub type RTCScene = *mut RTCSceneTy;
    /// `RTCGeometry`.
    pub type RTCGeometry = *mut RTCGeometryTy;

    /// `enum RTCError` (an unsigned int for GCC: no negative enumerator).
    pub type RTCError = c_uint;
    /// `RTC_ERROR_NONE`.
    pub const RTC_ERROR_NONE: RTCError = 0;
    /// `enum RTCDeviceProperty`.
    pub type RTCDeviceProperty = c_uint;
    /// `RTC_DEVICE_PROPERTY_VERSION` (e.g. 31305 for 3.13.5).
    pub const RTC_DEVICE_PROPERTY_VERSION: RTCDeviceProperty = 0;
    /// `enum RTCBuildQuality`.
    pub type RTCBuildQuality = c_uint;
    /// `RTC_BUILD_QUALITY_LOW`: the Morton builder.
    pub const RTC_BUILD_QUALITY_LOW: RTCBuildQuality = 0;
    /// `RTC_BUILD_QUALITY_MEDIUM`: binned SAH.
    pub const RTC_BUILD_QUALITY_MEDIUM: RTCBuildQuality = 1;
    /// `RTC_BUILD_QUALITY_REFIT`: a geometry's BVH refitted, not rebuilt, on commit.
    pub const RTC_BUILD_QUALITY_REFIT: RTCBuildQuality = 3;
    /// `enum RTCSceneFlags`.
    pub type RTCSceneFlags = c_uint;
    /// `RTC_SCENE_FLAG_NONE`.
    pub const RTC_SCENE_FLAG_NONE: RTCSceneFlags = 0;
    /// `RTC_SCENE_FLAG_DYNAMIC`: the scene is committed again after changes.
    pub const RTC_SCENE_FLAG_DYNAMIC: RTCSceneFlags = 1;
    /// `enum RTCGeometryType`.
    pub type RTCGeometryType = c_uint;
    /// `RTC_GEOMETRY_TYPE_TRIANGLE`.
    pub const RTC_GEOMETRY_TYPE_TRIANGLE: RTCGeometryType = 0;
    /// `RTC_GEOMETRY_TYPE_INSTANCE`: a scene instanced under a transform.
    pub const RTC_GEOMETRY_TYPE_INSTANCE: RTCGeometryType = 121;
    /// `enum RTCBufferType`.
    pub type RTCBufferType = c_uint;
    /// `RTC_BUFFER_TYPE_INDEX`.
    pub const RTC_BUFFER_TYPE_INDEX: RTCBufferType = 0;
    /// `RTC_BUFFER_TYPE_VERTEX`.
    pub const RTC_BUFFER_TYPE_VERTEX: RTCBufferType = 1;
    /// `enum RTCFormat`.
    pub type RTCFormat = c_uint;
    /// `RTC_FORMAT_UINT3`.
    pub const RTC_FORMAT_UINT3: RTCFormat = 0x5003;
    /// `RTC_FORMAT_FLOAT3`.
    pub const RTC_FORMAT_FLOAT3: RTCFormat = 0x9003;
    /// `RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR`: a 3×4 matrix as four columns of three floats.
    pub const RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR: RTCFormat = 0x9234;
    /// `enum RTCIntersectContextFlags`.
    pub type RTCIntersectContextFlags = c_uint;
    /// `RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT`.
    pub const RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT: RTCIntersectContextFlags = 0;
    /// `RTC_INTERSECT_CONTEXT_FLAG_COHERENT`.
    pub const RTC_INTERSECT_CONTEXT_FLAG_COHERENT: RTCIntersectContextFlags = 1;
    /// `RTC_INVALID_GEOMETRY_ID`.
    pub const RTC_INVALID_GEOMETRY_ID: c_uint = c_uint::MAX;

    /// `RTCErrorFunction`.
    pub type RTCErrorFunction =
        Option<unsafe extern "C" fn(user: *mut c_void, code: RTCError, str: *const c_char)>;
    /// `RTCMemoryMonitorFunction` (`ssize_t` is `isize` on the LP64 targets Embree runs on).
    pub type RTCMemoryMonitorFunction =
        Option<unsafe extern "C" fn(user: *mut c_void, bytes: isize, post: bool) -> bool>;
    /// `RTCFilterFunctionN` (never set here: always null).
    pub type RTCFilterFunctionN = Option<unsafe extern "C" fn(args: *const c_void)>;

    /// `struct RTCRay` (16-byte aligned).
    #[repr(C, align(16))]
    #[derive(Clone, Copy, Debug, Default)]
    pub struct RTCRay {
        /// Origin x.
        pub org_x: f32,
        /// Origin y.
        pub org_y: f32,
        /// Origin z.
        pub org_z: f32,
        /// Start of the ray segment.
        pub tnear: f32,
        /// Direction x.
        pub dir_x: f32,
        /// Direction y.
        pub dir_y: f32,
        /// Direction z.
        pub dir_z: f32,
        /// Motion-blur time.
        pub time: f32,
        /// End of the segment; the hit distance after a hit, −inf after an occlusion.
        pub tfar: f32,
        /// Ray mask.
        pub mask: c_uint,
        /// Ray id.
        pub id: c_uint,
        /// Ray flags.
        pub flags: c_uint,
    }

    /// `struct RTCHit` (16-byte aligned).
    #[repr(C, align(16))]
    #[derive(Clone, Copy, Debug, Default)]
    pub struct RTCHit {
        /// Geometric normal x (not normalized).
        pub ng_x: f32,
        /// Geometric normal y.
        pub ng_y: f32,
        /// Geometric normal z.
        pub ng_z: f32,
        /// Barycentric u.
        pub u: f32,
        /// Barycentric v.
        pub v: f32,
        /// Primitive id.
        pub prim_id: c_uint,
        /// Geometry id (`RTC_INVALID_GEOMETRY_ID` for a miss).
        pub geom_id: c_uint,
        /// Instance ids (`RTC_MAX_INSTANCE_LEVEL_COUNT` = 1).
        pub inst_id: [c_uint; 1],
    }

    /// `struct RTCRayHit`.
    #[repr(C)]
    #[derive(Clone, Copy, Debug, Default)]
    pub struct RTCRayHit {
        /// The ray.
        pub ray: RTCRay,
        /// The hit.
        pub hit: RTCHit,
    }

    /// `struct RTCIntersectContext` (no `instStackSize`, no `minWidthDistanceFactor` in this
    /// configuration).
    #[repr(C)]
    #[derive(Clone, Copy, Debug)]
    pub struct RTCIntersectContext {
        /// Coherent or incoherent rays.
        pub flags: RTCIntersectContextFlags,
        /// Filter function (null).
        pub filter: RTCFilterFunctionN,
        /// The instance id stack.
        pub inst_id: [c_uint; 1],
    }

    impl RTCIntersectContext {
        /// What the header's inline `rtcInitIntersectContext` writes: INCOHERENT, no filter,
        /// every instance id invalid.
        pub fn init() -> RTCIntersectContext {
            RTCIntersectContext {
                flags: RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT,
                filter: None,
                inst_id: [RTC_INVALID_GEOMETRY_ID; 1],
            }
        }
    }

    #[link(name = "embree3")]
    extern "C" {
        /// `rtcNewDevice`.
        pub fn rtcNewDevice(config: *const c_char) -> RTCDevice;
        /// `rtcReleaseDevice`.
        pub fn rtcReleaseDevice(device: RTCDevice);
        /// `rtcGetDeviceError`.
        pub fn rtcGetDeviceError(device: RTCDevice) -> RTCError;
        /// `rtcGetDeviceProperty`.
        pub fn rtcGetDeviceProperty(device: RTCDevice, prop: RTCDeviceProperty) -> isize;
        /// `rtcSetDeviceErrorFunction`.
        pub fn rtcSetDeviceErrorFunction(
            device: RTCDevice,
            error: RTCErrorFunction,
            user: *mut c_void,
        );
        /// `rtcSetDeviceMemoryMonitorFunction`.
        pub fn rtcSetDeviceMemoryMonitorFunction(
            device: RTCDevice,
            monitor: RTCMemoryMonitorFunction,
            user: *mut c_void,
        );
        /// `rtcNewScene`.
        pub fn rtcNewScene(device: RTCDevice) -> RTCScene;
        /// `rtcSetSceneBuildQuality`.
        pub fn rtcSetSceneBuildQuality(scene: RTCScene, quality: RTCBuildQuality);
        /// `rtcSetSceneFlags`.
        pub fn rtcSetSceneFlags(scene: RTCScene, flags: RTCSceneFlags);
        /// `rtcCommitScene`.
        pub fn rtcCommitScene(scene: RTCScene);
        /// `rtcReleaseScene`.
        pub fn rtcReleaseScene(scene: RTCScene);
        /// `rtcRetainScene`.
        pub fn rtcRetainScene(scene: RTCScene);
        /// `rtcRetainGeometry`.
        pub fn rtcRetainGeometry(geometry: RTCGeometry);
        /// `rtcAttachGeometry`.
        pub fn rtcAttachGeometry(scene: RTCScene, geometry: RTCGeometry) -> c_uint;
        /// `rtcNewGeometry`.
        pub fn rtcNewGeometry(device: RTCDevice, kind: RTCGeometryType) -> RTCGeometry;
        /// `rtcReleaseGeometry`.
        pub fn rtcReleaseGeometry(geometry: RTCGeometry);
        /// `rtcSetSharedGeometryBuffer`.
        pub fn rtcSetSharedGeometryBuffer(
            geometry: RTCGeometry,
            kind: RTCBufferType,
            slot: c_uint,
            format: RTCFormat,
            ptr: *const c_void,
            byte_offset: usize,
            byte_stride: usize,
            item_count: usize,
        );
        /// `rtcSetGeometryBuildQuality`.
        pub fn rtcSetGeometryBuildQuality(geometry: RTCGeometry, quality: RTCBuildQuality);
        /// `rtcUpdateGeometryBuffer`.
        pub fn rtcUpdateGeometryBuffer(geometry: RTCGeometry, kind: RTCBufferType, slot: c_uint);
        /// `rtcCommitGeometry`.
        pub fn rtcCommitGeometry(geometry: RTCGeometry);
        /// `rtcSetGeometryInstancedScene`.
        pub fn rtcSetGeometryInstancedScene(geometry: RTCGeometry, scene: RTCScene);
        /// `rtcSetGeometryTransform`.
        pub fn rtcSetGeometryTransform(
            geometry: RTCGeometry,
            time_step: c_uint,
            format: RTCFormat,
            xfm: *const c_void,
        );
        /// `rtcIntersect1`.
        pub fn rtcIntersect1(
            scene: RTCScene,
            context: *mut RTCIntersectContext,
            rayhit: *mut RTCRayHit,
        );
        /// `rtcOccluded1`.
        pub fn rtcOccluded1(scene: RTCScene, context: *mut RTCIntersectContext, ray: *mut RTCRay);
    }
}

/// What Embree reported, or why a call was refused before reaching it.
#[derive(Debug, thiserror::Error)]
pub enum EmbreeError {
    /// `rtcNewDevice` returned null.
    #[error("Embree could not create a device (`{config}`): error code {code}")]
    NoDevice {
        /// The configuration string.
        config: String,
        /// `rtcGetDeviceError(NULL)`.
        code: u32,
    },
    /// The error callback fired during a call.
    #[error("Embree error {code} during {during}: {message}")]
    Call {
        /// What was being done.
        during: &'static str,
        /// The `RTCError` code.
        code: u32,
        /// Embree's message.
        message: String,
    },
    /// A mesh Embree cannot take (indices out of range, counts past 32 bits, no triangle).
    #[error("mesh not usable by Embree: {0}")]
    Mesh(String),
}

/// Build quality of a scene (the two the harness and `emc compare` measure).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Quality {
    /// `RTC_BUILD_QUALITY_LOW`: Morton code builder to BVH8, 4-triangle leaves.
    Low,
    /// `RTC_BUILD_QUALITY_MEDIUM`: binned SAH to BVH8, 4-triangle leaves.
    Medium,
}

impl Quality {
    fn raw(self) -> sys::RTCBuildQuality {
        match self {
            Quality::Low => sys::RTC_BUILD_QUALITY_LOW,
            Quality::Medium => sys::RTC_BUILD_QUALITY_MEDIUM,
        }
    }
    /// The harness's configuration name (`low_morton`, `medium_binned_sah`).
    pub fn harness_name(self) -> &'static str {
        match self {
            Quality::Low => "low_morton",
            Quality::Medium => "medium_binned_sah",
        }
    }
}

/// What the callbacks write: live bytes the memory monitor counted, and errors seen.
#[derive(Debug, Default)]
struct DeviceState {
    memory: AtomicI64,
    errors: Mutex<Vec<(u32, String)>>,
}

unsafe extern "C" fn on_error(user: *mut c_void, code: sys::RTCError, message: *const c_char) {
    if user.is_null() {
        return;
    }
    // SAFETY: `user` is the `DeviceState` the device was registered with in `Device::new`; it is
    // boxed (fixed address) and outlives the device (released before the box is dropped).
    let state = unsafe { &*(user as *const DeviceState) };
    let text = if message.is_null() {
        String::from("(no message)")
    } else {
        // SAFETY: Embree passes a NUL-terminated string valid for the callback's duration.
        unsafe { CStr::from_ptr(message) }
            .to_string_lossy()
            .into_owned()
    };
    state
        .errors
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .push((code, text));
}

unsafe extern "C" fn on_memory(user: *mut c_void, bytes: isize, _post: bool) -> bool {
    if !user.is_null() {
        // SAFETY: as in `on_error`: the device's boxed state, alive while the device is.
        let state = unsafe { &*(user as *const DeviceState) };
        state.memory.fetch_add(bytes as i64, Ordering::Relaxed);
    }
    true
}

/// An Embree device with its error callback and memory monitor.
#[derive(Debug)]
pub struct Device {
    raw: sys::RTCDevice,
    threads: usize,
    /// Boxed so the callbacks' user pointer stays valid; dropped after the device is released.
    state: Box<DeviceState>,
}

// SAFETY: an Embree device is thread-safe (its API may be called from any thread, and the
// callbacks write only atomics and a mutex).
unsafe impl Send for Device {}
// SAFETY: as above; `&Device` only reaches thread-safe Embree calls and the synchronized state.
unsafe impl Sync for Device {}

impl Device {
    /// A device with `threads` build threads (`threads=N,verbose=0`, as the harness makes one per
    /// thread count), error callback and memory monitor set.
    pub fn new(threads: usize) -> Result<Device, EmbreeError> {
        let config = format!("threads={threads},verbose=0");
        let c = CString::new(config.clone()).map_err(|e| EmbreeError::NoDevice {
            config: config.clone(),
            code: e.nul_position() as u32,
        })?;
        // SAFETY: `c` is a NUL-terminated string alive for the call.
        let raw = unsafe { sys::rtcNewDevice(c.as_ptr()) };
        if raw.is_null() {
            // SAFETY: a null device asks for the error of the last failed device creation.
            let code = unsafe { sys::rtcGetDeviceError(core::ptr::null_mut()) };
            return Err(EmbreeError::NoDevice { config, code });
        }
        let state = Box::<DeviceState>::default();
        let user = &*state as *const DeviceState as *mut c_void;
        // SAFETY: `raw` is a live device; the callbacks match the C signatures and `user` points
        // to the boxed state, which outlives the device (see `Drop`).
        unsafe {
            sys::rtcSetDeviceErrorFunction(raw, Some(on_error), user);
            sys::rtcSetDeviceMemoryMonitorFunction(raw, Some(on_memory), user);
        }
        Ok(Device {
            raw,
            threads,
            state,
        })
    }

    /// The thread count the device was made with.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// The library's version as `major.minor.patch` (`rtcGetDeviceProperty`).
    pub fn version(&self) -> String {
        // SAFETY: `raw` is a live device; the property query has no other effect.
        let v = unsafe { sys::rtcGetDeviceProperty(self.raw, sys::RTC_DEVICE_PROPERTY_VERSION) };
        format!("{}.{}.{}", v / 10000, v / 100 % 100, v % 100)
    }

    /// Bytes the memory monitor counts as allocated by Embree right now.
    pub fn memory_bytes(&self) -> i64 {
        self.state.memory.load(Ordering::Relaxed)
    }

    /// The first error reported since the last check, as an error naming `during`.
    fn check(&self, during: &'static str) -> Result<(), EmbreeError> {
        let first = {
            let mut errs = self.state.errors.lock().unwrap_or_else(|e| e.into_inner());
            let first = errs.first().cloned();
            errs.clear();
            first
        };
        match first {
            Some((code, message)) => Err(EmbreeError::Call {
                during,
                code,
                message,
            }),
            None => Ok(()),
        }
    }
}

impl Drop for Device {
    fn drop(&mut self) {
        // SAFETY: `raw` is the live device made in `new`, released exactly once; scenes borrow the
        // device, so none outlives it.
        unsafe { sys::rtcReleaseDevice(self.raw) };
    }
}

/// A triangle mesh in the layout Embree's shared buffers read: packed `f32` xyz positions with
/// 16 bytes of padding at the end, and packed `u32` index triples.
#[derive(Debug, Clone)]
pub struct Mesh {
    positions: Vec<f32>,
    indices: Vec<u32>,
    vertex_count: usize,
}

impl Mesh {
    /// Copy an indexed mesh; fails on an index out of range, more than `u32::MAX` vertices or
    /// triangles, or no triangle.
    pub fn new(vertices: &[Vec3], indices: &[[u32; 3]]) -> Result<Mesh, EmbreeError> {
        if indices.is_empty() {
            return Err(EmbreeError::Mesh("no triangles".into()));
        }
        if vertices.len() > u32::MAX as usize || indices.len() > u32::MAX as usize {
            return Err(EmbreeError::Mesh(format!(
                "{} vertices and {} triangles exceed 32-bit counts",
                vertices.len(),
                indices.len()
            )));
        }
        if let Some((t, &ix)) = indices.iter().enumerate().find_map(|(t, tri)| {
            tri.iter()
                .find(|&&i| i as usize >= vertices.len())
                .map(|i| (t, i))
        }) {
            return Err(EmbreeError::Mesh(format!(
                "triangle {t} names vertex {ix} of {}",
                vertices.len()
            )));
        }
        let mut positions = Vec::with_capacity(3 * vertices.len() + 4);
        for v in vertices {
            positions.extend_from_slice(&[v.x, v.y, v.z]);
        }
        positions.extend_from_slice(&[0.0; 4]);
        Ok(Mesh {
            positions,
            indices: indices.iter().flatten().copied().collect(),
            vertex_count: vertices.len(),
        })
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }
}

/// A committed Embree scene over a [`Mesh`]'s shared buffers, traceable from many threads.
#[derive(Debug)]
pub struct Scene<'a> {
    device: &'a Device,
    mesh: &'a Mesh,
    raw: sys::RTCScene,
    /// The triangle geometry, retained for [`Scene::rebuild`].
    geometry: sys::RTCGeometry,
    quality: Quality,
    memory: i64,
}

// SAFETY: a committed scene may be traced from any number of threads at once (Embree's
// rtcIntersect1/rtcOccluded1 contract); the mutating calls (`rebuild`, drop) take `&mut self`
// or `self`, so they never race with tracing.
unsafe impl Sync for Scene<'_> {}
// SAFETY: the handles may be used and released from any thread.
unsafe impl Send for Scene<'_> {}

impl<'a> Scene<'a> {
    /// Build a scene as the harness's `build_scene` does, timing it from `rtcNewScene` to the
    /// end of `rtcCommitScene` (the harness starts its clock just before `rtcCommitScene`; the
    /// calls before it only record pointers). Returns the scene and the wall time.
    pub fn build(
        device: &'a Device,
        mesh: &'a Mesh,
        quality: Quality,
    ) -> Result<(Scene<'a>, Duration), EmbreeError> {
        device.check("an earlier call")?;
        let before = device.memory_bytes();
        let q = quality.raw();
        let t0 = Instant::now();
        // SAFETY: `device.raw` is live for 'a; the shared buffers point into `mesh`, which
        // outlives the scene ('a) and is never written while it exists: positions hold
        // `vertex_count` packed float triples plus 16 bytes of padding, indices hold
        // `triangle_count` packed u32 triples, all below `vertex_count` (checked in
        // `Mesh::new`). Where the harness releases the geometry after attaching it, the scene
        // keeps that reference for `rebuild` and releases it in `Drop`.
        let (raw, geometry) = unsafe {
            commit_shared(
                device,
                (&mesh.positions, mesh.vertex_count),
                &mesh.indices,
                (q, sys::RTC_SCENE_FLAG_NONE, q),
            )
        };
        let elapsed = t0.elapsed();
        let scene = Scene {
            device,
            mesh,
            raw,
            geometry,
            quality,
            memory: device.memory_bytes() - before,
        };
        device.check("building a scene")?;
        Ok((scene, elapsed))
    }

    /// Build again over the same buffers (the nearest analogue of `Accel::rebuild`): the
    /// vertex buffer marked updated, the geometry and the scene committed again. Returns the
    /// wall time.
    pub fn rebuild(&mut self) -> Result<Duration, EmbreeError> {
        let t0 = Instant::now();
        // SAFETY: the scene and geometry are live (owned by `self`), the shared buffers still
        // point into the borrowed mesh; `&mut self` excludes concurrent tracing.
        unsafe { recommit(self.raw, self.geometry) };
        let elapsed = t0.elapsed();
        self.device.check("rebuilding a scene")?;
        Ok(elapsed)
    }

    /// The build quality.
    pub fn quality(&self) -> Quality {
        self.quality
    }

    /// Bytes Embree allocated during the build (its memory monitor's count, as the harness's
    /// `mem_mb`).
    pub fn memory_bytes(&self) -> i64 {
        self.memory
    }

    /// The mesh the scene reads.
    pub fn mesh(&self) -> &Mesh {
        self.mesh
    }

    /// Closest hit of one ray through `rtcIntersect1` with `ctx`.
    #[inline]
    pub fn intersect(&self, ray: &Ray, ctx: &mut sys::RTCIntersectContext) -> Option<Hit> {
        intersect_raw(self.raw, ray, ctx)
    }

    /// Whether one ray is occluded, through `rtcOccluded1` with `ctx`.
    #[inline]
    pub fn occluded(&self, ray: &Ray, ctx: &mut sys::RTCIntersectContext) -> bool {
        occluded_raw(self.raw, ray, ctx)
    }
}

impl Drop for Scene<'_> {
    fn drop(&mut self) {
        // SAFETY: both handles are live and owned by this scene (the geometry's creation
        // reference, kept in `build`); each is released exactly once.
        unsafe {
            sys::rtcReleaseScene(self.raw);
            sys::rtcReleaseGeometry(self.geometry);
        }
    }
}

/// How an [`Animated`] scene takes moved vertices at its next commit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Update {
    /// The geometry's build quality `RTC_BUILD_QUALITY_REFIT`: its BVH refitted.
    Refit,
    /// `RTC_BUILD_QUALITY_LOW`: the Morton builder run again.
    Low,
}

impl Update {
    /// The row label.
    pub fn name(self) -> &'static str {
        match self {
            Update::Refit => "embree REFIT",
            Update::Low => "embree LOW",
        }
    }
}

/// A one-mesh scene whose vertices move between commits (Embree's dynamic-scene recipe: the
/// scene flagged `RTC_SCENE_FLAG_DYNAMIC` at build quality LOW, the geometry at the
/// [`Update`]'s quality, positions in a shared buffer that the scene owns, and per frame
/// `rtcUpdateGeometryBuffer`, `rtcCommitGeometry`, `rtcCommitScene`).
#[derive(Debug)]
pub struct Animated<'a> {
    device: &'a Device,
    /// Packed xyz plus 16 bytes of padding; never reallocated while the scene exists.
    positions: Box<[f32]>,
    indices: Box<[u32]>,
    raw: sys::RTCScene,
    geometry: sys::RTCGeometry,
}

// SAFETY: as for `Scene`: tracing takes `&self` (Embree's contract allows any number of
// threads), the buffer writes and commits take `&mut self`.
unsafe impl Sync for Animated<'_> {}
// SAFETY: the handles may be used and released from any thread.
unsafe impl Send for Animated<'_> {}

impl<'a> Animated<'a> {
    /// Build over `vertices` and `indices` (checked as [`Mesh::new`] checks them); returns the
    /// scene and the wall time of its first commit.
    pub fn build(
        device: &'a Device,
        vertices: &[Vec3],
        indices: &[[u32; 3]],
        update: Update,
    ) -> Result<(Animated<'a>, Duration), EmbreeError> {
        let mesh = Mesh::new(vertices, indices)?;
        device.check("an earlier call")?;
        let positions = mesh.positions.into_boxed_slice();
        let indices = mesh.indices.into_boxed_slice();
        let q = match update {
            Update::Refit => sys::RTC_BUILD_QUALITY_REFIT,
            Update::Low => sys::RTC_BUILD_QUALITY_LOW,
        };
        let t0 = Instant::now();
        // SAFETY: the device is live for 'a; the shared buffers point into the boxed slices,
        // which the scene owns and never reallocates, with the counts of `Mesh::new`'s checks
        // (positions: `vertex_count` triples plus 16 bytes; indices in range).
        let (raw, geometry) = unsafe {
            commit_shared(
                device,
                (&positions, mesh.vertex_count),
                &indices,
                (sys::RTC_BUILD_QUALITY_LOW, sys::RTC_SCENE_FLAG_DYNAMIC, q),
            )
        };
        let elapsed = t0.elapsed();
        let a = Animated {
            device,
            positions,
            indices,
            raw,
            geometry,
        };
        device.check("building an animated scene")?;
        Ok((a, elapsed))
    }

    /// Move the vertices (same count; the copy into the shared buffer is not timed) and
    /// commit; returns the wall time of `rtcUpdateGeometryBuffer` to the end of
    /// `rtcCommitScene`.
    pub fn update(&mut self, vertices: &[Vec3]) -> Result<Duration, EmbreeError> {
        if 3 * vertices.len() + 4 != self.positions.len() {
            return Err(EmbreeError::Mesh(format!(
                "{} vertices given, the scene has {}",
                vertices.len(),
                (self.positions.len() - 4) / 3
            )));
        }
        for (p, v) in self.positions.chunks_exact_mut(3).zip(vertices) {
            p.copy_from_slice(&[v.x, v.y, v.z]);
        }
        let t0 = Instant::now();
        // SAFETY: scene and geometry are live and owned by `self`; `&mut self` excludes
        // tracing during the commit; the buffer stays where it was.
        unsafe { recommit(self.raw, self.geometry) };
        let elapsed = t0.elapsed();
        self.device.check("committing an animated scene")?;
        Ok(elapsed)
    }

    /// Triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// Closest hit of one ray through `rtcIntersect1` with `ctx`.
    #[inline]
    pub fn intersect(&self, ray: &Ray, ctx: &mut sys::RTCIntersectContext) -> Option<Hit> {
        intersect_raw(self.raw, ray, ctx)
    }
}

impl Drop for Animated<'_> {
    fn drop(&mut self) {
        // SAFETY: both handles are live and owned by this scene; each is released once.
        unsafe {
            sys::rtcReleaseScene(self.raw);
            sys::rtcReleaseGeometry(self.geometry);
        }
    }
}

impl Tracer for Animated<'_> {
    /// Primary rays: one COHERENT context per thread.
    fn closest(&self, rays: &[Ray], threads: usize) -> (Vec<Option<Hit>>, Timing) {
        trace_closest(rays, threads, || context(true), |c, r| self.intersect(r, c))
    }
    /// Occlusion: one INCOHERENT context per thread.
    fn occluded(&self, rays: &[Ray], threads: usize) -> (u64, Timing) {
        trace_occluded(
            rays,
            threads,
            || context(false),
            |c, r| occluded_raw(self.raw, r, c),
        )
    }
}

/// A two-level scene: one mesh as a scene of its own (MEDIUM, as [`Scene`] builds it) and a
/// top-level scene of instances of it (`RTC_GEOMETRY_TYPE_INSTANCE`, one per transform, ids
/// in order), at the top-level quality given (LOW with `RTC_SCENE_FLAG_DYNAMIC`, or MEDIUM).
#[derive(Debug)]
pub struct Instanced<'a> {
    device: &'a Device,
    /// The instanced mesh's scene (its geometry's handle kept for release).
    blas: (sys::RTCScene, sys::RTCGeometry),
    top: sys::RTCScene,
    instances: Vec<sys::RTCGeometry>,
    quality: Quality,
    memory: i64,
}

// SAFETY: as for `Scene`: tracing takes `&self`, the transform updates and commits `&mut self`.
unsafe impl Sync for Instanced<'_> {}
// SAFETY: the handles may be used and released from any thread.
unsafe impl Send for Instanced<'_> {}

/// `m` as Embree's column-major 3×4 floats.
fn float3x4(m: &glam::Affine3A) -> [f32; 12] {
    let (x, y, z, t) = (
        m.matrix3.x_axis,
        m.matrix3.y_axis,
        m.matrix3.z_axis,
        m.translation,
    );
    [x.x, x.y, x.z, y.x, y.y, y.z, z.x, z.y, z.z, t.x, t.y, t.z]
}

impl<'a> Instanced<'a> {
    /// The mesh's scene, built and committed (not timed: it is what every instance shares).
    pub fn blas(device: &'a Device, mesh: &'a Mesh) -> Result<(Scene<'a>, Duration), EmbreeError> {
        Scene::build(device, mesh, Quality::Medium)
    }

    /// A top-level scene of `transforms.len()` instances of `blas`, timed from `rtcNewScene`
    /// through every instance's creation to the end of `rtcCommitScene` (cold), and the commit
    /// alone.
    pub fn build(
        device: &'a Device,
        blas: &Scene<'a>,
        transforms: &[glam::Affine3A],
        quality: Quality,
    ) -> Result<(Instanced<'a>, Duration, Duration), EmbreeError> {
        device.check("an earlier call")?;
        if transforms.len() >= u32::MAX as usize {
            return Err(EmbreeError::Mesh(format!("{} instances", transforms.len())));
        }
        let before = device.memory_bytes();
        let t0 = Instant::now();
        // SAFETY: the device and the instanced scene are live (borrowed for 'a; Embree keeps
        // its own reference to the instanced scene); each transform is 12 floats read during
        // the call only.
        let (top, instances, commit) = unsafe {
            let top = sys::rtcNewScene(device.raw);
            let (q, flags) = match quality {
                Quality::Low => (sys::RTC_BUILD_QUALITY_LOW, sys::RTC_SCENE_FLAG_DYNAMIC),
                Quality::Medium => (sys::RTC_BUILD_QUALITY_MEDIUM, sys::RTC_SCENE_FLAG_NONE),
            };
            sys::rtcSetSceneBuildQuality(top, q);
            sys::rtcSetSceneFlags(top, flags);
            let mut instances = Vec::with_capacity(transforms.len());
            for m in transforms {
                let g = sys::rtcNewGeometry(device.raw, sys::RTC_GEOMETRY_TYPE_INSTANCE);
                sys::rtcSetGeometryInstancedScene(g, blas.raw);
                let x = float3x4(m);
                sys::rtcSetGeometryTransform(
                    g,
                    0,
                    sys::RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR,
                    x.as_ptr() as *const c_void,
                );
                sys::rtcCommitGeometry(g);
                sys::rtcAttachGeometry(top, g);
                instances.push(g);
            }
            let c0 = Instant::now();
            sys::rtcCommitScene(top);
            (top, instances, c0.elapsed())
        };
        let cold = t0.elapsed();
        // SAFETY: the instanced mesh scene gains a reference so that it outlives this scene
        // whatever the caller drops first: `blas` here is only borrowed, so the handles are
        // retained and released in `Drop`.
        unsafe {
            sys::rtcRetainScene(blas.raw);
            sys::rtcRetainGeometry(blas.geometry);
        }
        let s = Instanced {
            device,
            blas: (blas.raw, blas.geometry),
            top,
            instances,
            quality,
            memory: device.memory_bytes() - before,
        };
        device.check("building an instanced scene")?;
        Ok((s, cold, commit))
    }

    /// Move every instance (as many transforms as instances) and commit: returns the wall
    /// time of the whole update (`rtcSetGeometryTransform` + `rtcCommitGeometry` per
    /// instance, then `rtcCommitScene`) and of `rtcCommitScene` alone.
    pub fn update(
        &mut self,
        transforms: &[glam::Affine3A],
    ) -> Result<(Duration, Duration), EmbreeError> {
        if transforms.len() != self.instances.len() {
            return Err(EmbreeError::Mesh(format!(
                "{} transforms for {} instances",
                transforms.len(),
                self.instances.len()
            )));
        }
        let t0 = Instant::now();
        // SAFETY: every handle is live and owned by `self`; `&mut self` excludes tracing; each
        // transform is read during its call only.
        let commit = unsafe {
            for (&g, m) in self.instances.iter().zip(transforms) {
                let x = float3x4(m);
                sys::rtcSetGeometryTransform(
                    g,
                    0,
                    sys::RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR,
                    x.as_ptr() as *const c_void,
                );
                sys::rtcCommitGeometry(g);
            }
            let c0 = Instant::now();
            sys::rtcCommitScene(self.top);
            c0.elapsed()
        };
        let all = t0.elapsed();
        self.device.check("updating an instanced scene")?;
        Ok((all, commit))
    }

    /// The top-level build quality.
    pub fn quality(&self) -> Quality {
        self.quality
    }

    /// Bytes Embree allocated for the top level and its instances.
    pub fn memory_bytes(&self) -> i64 {
        self.memory
    }

    /// Closest hit of one ray (instance id = the instance's index, geometry id 0).
    #[inline]
    pub fn intersect(&self, ray: &Ray, ctx: &mut sys::RTCIntersectContext) -> Option<Hit> {
        intersect_raw(self.top, ray, ctx)
    }
}

impl Drop for Instanced<'_> {
    fn drop(&mut self) {
        // SAFETY: every handle is live and owned by this value (the instances' creation
        // references, the top scene's, and the references retained on the mesh's scene and
        // geometry in `build`); each is released once, the top scene before what it instances.
        unsafe {
            sys::rtcReleaseScene(self.top);
            for &g in &self.instances {
                sys::rtcReleaseGeometry(g);
            }
            sys::rtcReleaseScene(self.blas.0);
            sys::rtcReleaseGeometry(self.blas.1);
        }
    }
}

impl Tracer for Instanced<'_> {
    /// Primary rays: one COHERENT context per thread.
    fn closest(&self, rays: &[Ray], threads: usize) -> (Vec<Option<Hit>>, Timing) {
        trace_closest(rays, threads, || context(true), |c, r| self.intersect(r, c))
    }
    /// Occlusion: one INCOHERENT context per thread.
    fn occluded(&self, rays: &[Ray], threads: usize) -> (u64, Timing) {
        trace_occluded(
            rays,
            threads,
            || context(false),
            |c, r| occluded_raw(self.top, r, c),
        )
    }
}

/// A scene of one triangle geometry over shared buffers (`positions`: packed xyz of
/// `vertex_count` vertices plus 16 bytes of padding; `indices`: packed triples), committed at
/// the given (scene quality, scene flags, geometry quality). The geometry keeps its creation
/// reference, released by the caller with the scene.
///
/// # Safety
/// `device` is live; both buffers outlive the scene and are not written while Embree reads
/// them; every index is below `vertex_count` (as [`Mesh::new`] checks).
unsafe fn commit_shared(
    device: &Device,
    (positions, vertex_count): (&[f32], usize),
    indices: &[u32],
    (scene_quality, flags, geometry_quality): (
        sys::RTCBuildQuality,
        sys::RTCSceneFlags,
        sys::RTCBuildQuality,
    ),
) -> (sys::RTCScene, sys::RTCGeometry) {
    // SAFETY: the caller's contract above.
    unsafe {
        let raw = sys::rtcNewScene(device.raw);
        sys::rtcSetSceneBuildQuality(raw, scene_quality);
        sys::rtcSetSceneFlags(raw, flags);
        let g = sys::rtcNewGeometry(device.raw, sys::RTC_GEOMETRY_TYPE_TRIANGLE);
        sys::rtcSetSharedGeometryBuffer(
            g,
            sys::RTC_BUFFER_TYPE_VERTEX,
            0,
            sys::RTC_FORMAT_FLOAT3,
            positions.as_ptr() as *const c_void,
            0,
            3 * size_of::<f32>(),
            vertex_count,
        );
        sys::rtcSetSharedGeometryBuffer(
            g,
            sys::RTC_BUFFER_TYPE_INDEX,
            0,
            sys::RTC_FORMAT_UINT3,
            indices.as_ptr() as *const c_void,
            0,
            3 * size_of::<u32>(),
            indices.len() / 3,
        );
        sys::rtcSetGeometryBuildQuality(g, geometry_quality);
        sys::rtcCommitGeometry(g);
        sys::rtcAttachGeometry(raw, g);
        sys::rtcCommitScene(raw);
        (raw, g)
    }
}

/// The vertex buffer marked updated, the geometry and the scene committed again.
///
/// # Safety
/// `raw` and `geometry` are live and attached; nothing traces the scene meanwhile.
unsafe fn recommit(raw: sys::RTCScene, geometry: sys::RTCGeometry) {
    // SAFETY: the caller's contract above.
    unsafe {
        sys::rtcUpdateGeometryBuffer(geometry, sys::RTC_BUFFER_TYPE_VERTEX, 0);
        sys::rtcCommitGeometry(geometry);
        sys::rtcCommitScene(raw);
    }
}

/// Whether one ray is occluded in a committed scene.
#[inline]
fn occluded_raw(raw: sys::RTCScene, ray: &Ray, ctx: &mut sys::RTCIntersectContext) -> bool {
    let mut r = to_rtc(ray);
    // SAFETY: callers pass a committed, live scene; `ctx` and `r` are valid structs of the C
    // layout, borrowed for the call only.
    unsafe { sys::rtcOccluded1(raw, ctx, &mut r) };
    r.tfar < 0.0
}

/// Closest hit of one ray in a committed scene.
#[inline]
fn intersect_raw(raw: sys::RTCScene, ray: &Ray, ctx: &mut sys::RTCIntersectContext) -> Option<Hit> {
    let mut rh = sys::RTCRayHit {
        ray: to_rtc(ray),
        hit: sys::RTCHit {
            geom_id: sys::RTC_INVALID_GEOMETRY_ID,
            prim_id: sys::RTC_INVALID_GEOMETRY_ID,
            ..sys::RTCHit::default()
        },
    };
    // SAFETY: callers pass a committed, live scene; `ctx` and `rh` are valid, aligned,
    // writable structs of the C layout, borrowed for the call only.
    unsafe { sys::rtcIntersect1(raw, ctx, &mut rh) };
    // Embree's instance id is RTC_INVALID_GEOMETRY_ID (u32::MAX, Hit::NO_INSTANCE) for a
    // hit not reached through an instance.
    (rh.hit.geom_id != sys::RTC_INVALID_GEOMETRY_ID).then_some(Hit {
        t: rh.ray.tfar,
        prim: rh.hit.prim_id,
        u: rh.hit.u,
        v: rh.hit.v,
        geom: rh.hit.geom_id,
        instance: rh.hit.inst_id[0],
    })
}

/// The harness's ray: origin, direction, the interval, time 0, the ray's mask (all ones for
/// the protocol's rays, as the harness), id 0, flags 0.
#[inline]
fn to_rtc(r: &Ray) -> sys::RTCRay {
    sys::RTCRay {
        org_x: r.origin.x,
        org_y: r.origin.y,
        org_z: r.origin.z,
        tnear: r.tnear,
        dir_x: r.dir.x,
        dir_y: r.dir.y,
        dir_z: r.dir.z,
        time: 0.0,
        tfar: r.tfar,
        mask: r.mask,
        id: 0,
        flags: 0,
    }
}

/// An intersect context as the harness's worker makes it: initialised, then flagged.
fn context(coherent: bool) -> sys::RTCIntersectContext {
    let mut c = sys::RTCIntersectContext::init();
    c.flags = if coherent {
        sys::RTC_INTERSECT_CONTEXT_FLAG_COHERENT
    } else {
        sys::RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT
    };
    c
}

impl Tracer for Scene<'_> {
    /// Primary rays: one COHERENT context per thread.
    fn closest(&self, rays: &[Ray], threads: usize) -> (Vec<Option<Hit>>, Timing) {
        trace_closest(rays, threads, || context(true), |c, r| self.intersect(r, c))
    }
    /// AO rays: one INCOHERENT context per thread.
    fn occluded(&self, rays: &[Ray], threads: usize) -> (u64, Timing) {
        trace_occluded(
            rays,
            threads,
            || context(false),
            |c, r| Scene::occluded(self, r, c),
        )
    }
}
