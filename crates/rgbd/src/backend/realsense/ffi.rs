//! The only unsafe code of the crate: librealsense2's C API, loaded at run time with
//! `libloading`, and safe owners around its handles.
//!
//! Every function is declared by hand from librealsense's public C headers
//! (`rs.h`, `rs_context.h`, `rs_device.h`, `rs_sensor.h`, `rs_frame.h`,
//! `rs_option.h`, `rs_advanced_mode.h`, `rs_internal.h`; API 2.x). Every call passes
//! an `rs2_error**` and every error is turned into an [`RsError`] naming the function
//! and librealsense's message. Every handle the library hands out is owned by a Rust
//! value whose `Drop` calls the matching `rs2_delete_*` / `rs2_release_frame`.
//!
//! Thread safety: librealsense's contexts, devices, sensors, frame queues and frames
//! may be used from any thread (the library locks internally); the backend still
//! serialises the open/start/stop/close of one sensor behind its own mutex.

use std::collections::BTreeMap;
use std::ffi::{CStr, CString, c_char, c_int, c_uint, c_void};
use std::marker::PhantomData;
use std::path::Path;
use std::ptr;
use std::sync::{Arc, Mutex, PoisonError};

/// Longest librealsense error message an [`RsError`] keeps, in characters.
const MESSAGE_CHARS: usize = 400;

/// `RS2_CAMERA_INFO_*` values used by the backend.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum CameraInfo {
    /// `RS2_CAMERA_INFO_NAME`.
    Name = 0,
    /// `RS2_CAMERA_INFO_SERIAL_NUMBER`.
    SerialNumber = 1,
    /// `RS2_CAMERA_INFO_PRODUCT_LINE`.
    ProductLine = 10,
}

/// `RS2_STREAM_DEPTH`.
pub(crate) const STREAM_DEPTH: c_int = 1;
/// `RS2_STREAM_COLOR`.
pub(crate) const STREAM_COLOR: c_int = 2;
/// `RS2_FORMAT_Z16`.
pub(crate) const FORMAT_Z16: c_int = 1;
/// `RS2_FORMAT_RGB8`.
pub(crate) const FORMAT_RGB8: c_int = 5;
/// `RS2_FORMAT_BGR8`.
pub(crate) const FORMAT_BGR8: c_int = 6;
/// `RS2_FORMAT_RGBA8`.
pub(crate) const FORMAT_RGBA8: c_int = 7;
/// `RS2_FORMAT_BGRA8`.
pub(crate) const FORMAT_BGRA8: c_int = 8;
/// `RS2_OPTION_DEPTH_UNITS`.
pub(crate) const OPTION_DEPTH_UNITS: c_int = 28;
/// `RS2_OPTION_STEREO_BASELINE`: the depth sensor's baseline in millimetres.
pub(crate) const OPTION_STEREO_BASELINE: c_int = 40;
/// `RS2_EXTENSION_ADVANCED_MODE`.
const EXTENSION_ADVANCED_MODE: c_int = 13;
/// `RS2_TIMESTAMP_DOMAIN_HARDWARE_CLOCK`: the camera's own clock, from its power-on.
const TIMESTAMP_DOMAIN_HARDWARE_CLOCK: c_int = 0;
/// `RS2_TIMESTAMP_DOMAIN_SYSTEM_TIME`: the host's clock when the frame arrived.
const TIMESTAMP_DOMAIN_SYSTEM_TIME: c_int = 1;
/// `RS2_TIMESTAMP_DOMAIN_GLOBAL_TIME`: the camera's clock mapped onto the host's.
const TIMESTAMP_DOMAIN_GLOBAL_TIME: c_int = 2;

macro_rules! opaque {
    ($($name:ident),*) => {$(
        #[repr(C)]
        pub(crate) struct $name {
            _private: [u8; 0],
        }
    )*};
}
opaque!(
    RawError,
    RawContext,
    RawDeviceList,
    RawDevice,
    RawSensorList,
    RawSensor,
    RawProfileList,
    RawProfile,
    RawFrameQueue,
    RawFrame,
    RawOptions,
    RawBuffer
);

/// `rs2_intrinsics`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct RsIntrinsics {
    pub(crate) width: c_int,
    pub(crate) height: c_int,
    pub(crate) ppx: f32,
    pub(crate) ppy: f32,
    pub(crate) fx: f32,
    pub(crate) fy: f32,
    /// `rs2_distortion`.
    pub(crate) model: c_int,
    pub(crate) coeffs: [f32; 5],
}

/// `rs2_extrinsics`: column-major rotation, translation in metres.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct RsExtrinsics {
    pub(crate) rotation: [f32; 9],
    pub(crate) translation: [f32; 3],
}

/// `rs2_video_stream` (`rs_internal.h`).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(crate) struct RsVideoStream {
    pub(crate) stream: c_int,
    pub(crate) index: c_int,
    pub(crate) uid: c_int,
    pub(crate) width: c_int,
    pub(crate) height: c_int,
    pub(crate) fps: c_int,
    pub(crate) bpp: c_int,
    pub(crate) format: c_int,
    pub(crate) intrinsics: RsIntrinsics,
}

/// `rs2_software_video_frame` (`rs_internal.h`, with the trailing `depth_units` of
/// current releases; older ones ignore it).
#[repr(C)]
struct RsSoftwareVideoFrame {
    pixels: *mut c_void,
    deleter: extern "C" fn(*mut c_void),
    stride: c_int,
    bpp: c_int,
    timestamp_ms: f64,
    domain: c_int,
    frame_number: c_int,
    profile: *const RawProfile,
    depth_units: f32,
}

type DevicesChanged = extern "C" fn(*mut RawDeviceList, *mut RawDeviceList, *mut c_void);

macro_rules! api {
    ($( fn $name:ident ( $($arg:ty),* ) $(-> $ret:ty)? ; )*) => {
        /// The librealsense functions the backend calls.
        #[allow(non_snake_case)]
        struct Api {
            $( $name: unsafe extern "C" fn($($arg),*) $(-> $ret)?, )*
        }

        impl Api {
            /// Looks every function up; the first missing one is the error.
            fn load(lib: &libloading::Library) -> Result<Self, String> {
                Ok(Self {
                    $( $name: {
                        // SAFETY: the type is the function's C signature from the headers.
                        let symbol = unsafe {
                            lib.get::<unsafe extern "C" fn($($arg),*) $(-> $ret)?>(
                                concat!(stringify!($name), "\0").as_bytes(),
                            )
                        };
                        *symbol.map_err(|e| format!("{}: {e}", stringify!($name)))?
                    }, )*
                })
            }
        }
    };
}

api! {
    fn rs2_get_api_version(*mut *mut RawError) -> c_int;
    fn rs2_get_error_message(*const RawError) -> *const c_char;
    fn rs2_get_failed_function(*const RawError) -> *const c_char;
    fn rs2_free_error(*mut RawError);
    fn rs2_create_context(c_int, *mut *mut RawError) -> *mut RawContext;
    fn rs2_delete_context(*mut RawContext);
    fn rs2_set_devices_changed_callback(*const RawContext, DevicesChanged, *mut c_void, *mut *mut RawError);
    fn rs2_query_devices(*const RawContext, *mut *mut RawError) -> *mut RawDeviceList;
    fn rs2_get_device_count(*const RawDeviceList, *mut *mut RawError) -> c_int;
    fn rs2_create_device(*const RawDeviceList, c_int, *mut *mut RawError) -> *mut RawDevice;
    fn rs2_device_list_contains(*const RawDeviceList, *const RawDevice, *mut *mut RawError) -> c_int;
    fn rs2_delete_device_list(*mut RawDeviceList);
    fn rs2_delete_device(*mut RawDevice);
    fn rs2_supports_device_info(*const RawDevice, c_int, *mut *mut RawError) -> c_int;
    fn rs2_get_device_info(*const RawDevice, c_int, *mut *mut RawError) -> *const c_char;
    fn rs2_query_sensors(*const RawDevice, *mut *mut RawError) -> *mut RawSensorList;
    fn rs2_get_sensors_count(*const RawSensorList, *mut *mut RawError) -> c_int;
    fn rs2_create_sensor(*const RawSensorList, c_int, *mut *mut RawError) -> *mut RawSensor;
    fn rs2_delete_sensor_list(*mut RawSensorList);
    fn rs2_delete_sensor(*mut RawSensor);
    fn rs2_get_stream_profiles(*mut RawSensor, *mut *mut RawError) -> *mut RawProfileList;
    fn rs2_get_active_streams(*mut RawSensor, *mut *mut RawError) -> *mut RawProfileList;
    fn rs2_get_stream_profiles_count(*const RawProfileList, *mut *mut RawError) -> c_int;
    fn rs2_get_stream_profile(*const RawProfileList, c_int, *mut *mut RawError) -> *const RawProfile;
    fn rs2_delete_stream_profiles_list(*mut RawProfileList);
    fn rs2_get_stream_profile_data(*const RawProfile, *mut c_int, *mut c_int, *mut c_int, *mut c_int, *mut c_int, *mut *mut RawError);
    fn rs2_get_video_stream_resolution(*const RawProfile, *mut c_int, *mut c_int, *mut *mut RawError);
    fn rs2_get_video_stream_intrinsics(*const RawProfile, *mut RsIntrinsics, *mut *mut RawError);
    fn rs2_get_extrinsics(*const RawProfile, *const RawProfile, *mut RsExtrinsics, *mut *mut RawError);
    fn rs2_register_extrinsics(*const RawProfile, *const RawProfile, RsExtrinsics, *mut *mut RawError);
    fn rs2_get_option(*const RawOptions, c_int, *mut *mut RawError) -> f32;
    fn rs2_open(*mut RawSensor, *const RawProfile, *mut *mut RawError);
    fn rs2_start_queue(*const RawSensor, *mut RawFrameQueue, *mut *mut RawError);
    fn rs2_stop(*const RawSensor, *mut *mut RawError);
    fn rs2_close(*const RawSensor, *mut *mut RawError);
    fn rs2_create_frame_queue(c_int, *mut *mut RawError) -> *mut RawFrameQueue;
    fn rs2_delete_frame_queue(*mut RawFrameQueue);
    fn rs2_try_wait_for_frame(*mut RawFrameQueue, c_uint, *mut *mut RawFrame, *mut *mut RawError) -> c_int;
    fn rs2_poll_for_frame(*mut RawFrameQueue, *mut *mut RawFrame, *mut *mut RawError) -> c_int;
    fn rs2_release_frame(*mut RawFrame);
    fn rs2_get_frame_data(*const RawFrame, *mut *mut RawError) -> *const c_void;
    fn rs2_get_frame_data_size(*const RawFrame, *mut *mut RawError) -> c_int;
    fn rs2_get_frame_width(*const RawFrame, *mut *mut RawError) -> c_int;
    fn rs2_get_frame_height(*const RawFrame, *mut *mut RawError) -> c_int;
    fn rs2_get_frame_stride_in_bytes(*const RawFrame, *mut *mut RawError) -> c_int;
    fn rs2_get_frame_stream_profile(*const RawFrame, *mut *mut RawError) -> *const RawProfile;
    fn rs2_get_frame_timestamp(*const RawFrame, *mut *mut RawError) -> f64;
    fn rs2_get_frame_timestamp_domain(*const RawFrame, *mut *mut RawError) -> c_int;
    fn rs2_is_device_extendable_to(*const RawDevice, c_int, *mut *mut RawError) -> c_int;
    fn rs2_is_enabled(*mut RawDevice, *mut c_int, *mut *mut RawError);
    fn rs2_load_json(*mut RawDevice, *const c_void, c_uint, *mut *mut RawError);
    fn rs2_serialize_json(*mut RawDevice, *mut *mut RawError) -> *mut RawBuffer;
    fn rs2_get_raw_data(*const RawBuffer, *mut *mut RawError) -> *const u8;
    fn rs2_get_raw_data_size(*const RawBuffer, *mut *mut RawError) -> c_int;
    fn rs2_delete_raw_data(*const RawBuffer);
    fn rs2_create_software_device(*mut *mut RawError) -> *mut RawDevice;
    fn rs2_software_device_add_sensor(*mut RawDevice, *const c_char, *mut *mut RawError) -> *mut RawSensor;
    fn rs2_software_device_register_info(*mut RawDevice, c_int, *const c_char, *mut *mut RawError);
    fn rs2_software_sensor_add_video_stream(*mut RawSensor, RsVideoStream, *mut *mut RawError) -> *mut RawProfile;
    fn rs2_software_sensor_add_read_only_option(*mut RawSensor, c_int, f32, *mut *mut RawError);
    fn rs2_software_sensor_on_video_frame(*mut RawSensor, RsSoftwareVideoFrame, *mut *mut RawError);
    fn rs2_context_add_software_device(*mut RawContext, *mut RawDevice, *mut *mut RawError);
}

/// A failed librealsense call: the function and librealsense's message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{function}: {message}")]
pub struct RsError {
    /// The C function that failed (as librealsense names it when it says).
    pub function: String,
    /// librealsense's message, at most 400 characters.
    pub message: String,
}

/// A loaded librealsense2 and its function table.
pub(crate) struct Lib {
    api: Api,
    version: c_int,
    // Last: the functions above point into it.
    _library: libloading::Library,
}

impl std::fmt::Debug for Lib {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Lib")
            .field("version", &self.version)
            .finish()
    }
}

/// Calls a librealsense function with a trailing `rs2_error**` and checks it.
macro_rules! call {
    ($lib:expr, $f:ident ( $($arg:expr),* $(,)? )) => {{
        let lib: &Lib = &$lib;
        let mut err: *mut RawError = ptr::null_mut();
        // SAFETY: the arguments are live handles owned by the caller (or out-pointers
        // to locals), matching the C signature.
        let result = unsafe { (lib.api.$f)($($arg,)* &mut err) };
        lib.check(stringify!($f), result, err)
    }};
}

/// Calls a pointer-returning function and refuses a null result.
macro_rules! call_ptr {
    ($lib:expr, $f:ident ( $($arg:expr),* $(,)? )) => {{
        let lib: &Lib = &$lib;
        call!(lib, $f($($arg),*)).and_then(|p| lib.non_null(stringify!($f), p))
    }};
}

impl Lib {
    /// Opens the library at `path` (a path or a bare name for the loader's search),
    /// looks up every function and reads the API version.
    pub(crate) fn open(path: &Path) -> Result<Arc<Self>, String> {
        // SAFETY: loading runs the library's initialisers; librealsense2 (or a module
        // embedding it) has no initialiser with preconditions on the caller.
        let library = unsafe { libloading::Library::new(path) }.map_err(|e| e.to_string())?;
        let api = Api::load(&library).map_err(|e| format!("missing function {e}"))?;
        let mut lib = Self {
            api,
            version: 0,
            _library: library,
        };
        lib.version = call!(lib, rs2_get_api_version()).map_err(|e| e.to_string())?;
        Ok(Arc::new(lib))
    }

    /// The API version the library reports: major * 10000 + minor * 100 + patch.
    pub(crate) fn version(&self) -> i32 {
        self.version
    }

    fn check<T>(&self, function: &str, result: T, err: *mut RawError) -> Result<T, RsError> {
        if err.is_null() {
            return Ok(result);
        }
        // SAFETY: `err` is an error librealsense just returned; it is freed once below.
        let (message, failed) = unsafe {
            (
                text((self.api.rs2_get_error_message)(err)),
                text((self.api.rs2_get_failed_function)(err)),
            )
        };
        // SAFETY: as above; not used afterwards.
        unsafe { (self.api.rs2_free_error)(err) };
        let function = match failed {
            Some(f) if !f.is_empty() && f != function => format!("{function} ({f})"),
            _ => function.to_owned(),
        };
        let message = message.unwrap_or_default();
        let message = match message.char_indices().nth(MESSAGE_CHARS) {
            Some((end, _)) => format!("{}…", &message[..end]),
            None => message,
        };
        Err(RsError { function, message })
    }

    fn non_null<T>(&self, function: &str, p: *mut T) -> Result<*mut T, RsError> {
        if p.is_null() {
            Err(RsError {
                function: function.to_owned(),
                message: "returned null".to_owned(),
            })
        } else {
            Ok(p)
        }
    }
}

/// Loads a library with `RTLD_NOW | RTLD_GLOBAL`, so libraries loaded later resolve
/// their undefined symbols against it.
#[cfg(unix)]
pub(crate) fn open_global(path: &Path) -> Result<libloading::os::unix::Library, String> {
    use libloading::os::unix::{Library, RTLD_GLOBAL, RTLD_NOW};
    // SAFETY: as for `Lib::open`: loading runs initialisers without caller preconditions.
    unsafe { Library::open(Some(path), RTLD_NOW | RTLD_GLOBAL) }.map_err(|e| e.to_string())
}

/// A C string as owned text, `None` for null.
///
/// # Safety
/// `p` is null or a NUL-terminated string valid for the duration of the call.
unsafe fn text(p: *const c_char) -> Option<String> {
    if p.is_null() {
        None
    } else {
        // SAFETY: the caller's contract.
        Some(unsafe { CStr::from_ptr(p) }.to_string_lossy().into_owned())
    }
}

fn c_string(function: &str, s: &str) -> Result<CString, RsError> {
    CString::new(s).map_err(|_| RsError {
        function: function.to_owned(),
        message: format!("argument {s:?} contains a NUL byte"),
    })
}

/// Called by librealsense on its own thread when devices come or go.
type ChangeHandler = dyn Fn(DeviceList, DeviceList) + Send + Sync;

struct CallbackState {
    lib: Arc<Lib>,
    handler: Box<ChangeHandler>,
}

extern "C" fn devices_changed(
    removed: *mut RawDeviceList,
    added: *mut RawDeviceList,
    user: *mut c_void,
) {
    // SAFETY: `user` is the `CallbackState` the owning `Context` keeps alive until
    // after `rs2_delete_context`, which stops the callbacks.
    let state = unsafe { &*user.cast::<CallbackState>() };
    // The callee owns both lists (librealsense's own C++ wrapper deletes them).
    let wrap = |raw: *mut RawDeviceList| {
        (!raw.is_null()).then(|| DeviceList {
            lib: Arc::clone(&state.lib),
            raw,
        })
    };
    let (removed, added) = (wrap(removed), wrap(added));
    if let (Some(removed), Some(added)) = (removed, added) {
        // A panic must not unwind into C; the handler reports its own failures.
        let _ = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            (state.handler)(removed, added);
        }));
    }
}

/// `rs2_context`, with the hot-plug callback it may carry.
pub(crate) struct Context {
    lib: Arc<Lib>,
    raw: *mut RawContext,
    callback: Option<Box<CallbackState>>,
}

// SAFETY: librealsense contexts are internally synchronised.
unsafe impl Send for Context {}
// SAFETY: as above.
unsafe impl Sync for Context {}

impl Context {
    /// A new context for the library's own API version.
    pub(crate) fn new(lib: &Arc<Lib>) -> Result<Self, RsError> {
        let raw = call_ptr!(lib, rs2_create_context(lib.version))?;
        Ok(Self {
            lib: Arc::clone(lib),
            raw,
            callback: None,
        })
    }

    /// The devices librealsense currently sees (software devices are not listed).
    pub(crate) fn query_devices(&self) -> Result<DeviceList, RsError> {
        let raw = call_ptr!(self.lib, rs2_query_devices(self.raw))?;
        Ok(DeviceList {
            lib: Arc::clone(&self.lib),
            raw,
        })
    }

    /// Installs `handler(removed, added)` as the devices-changed callback (replacing
    /// any earlier one, which stays alive until the context is dropped).
    pub(crate) fn on_devices_changed(
        &mut self,
        handler: Box<ChangeHandler>,
    ) -> Result<(), RsError> {
        let state = Box::new(CallbackState {
            lib: Arc::clone(&self.lib),
            handler,
        });
        let user = ptr::from_ref::<CallbackState>(&state)
            .cast_mut()
            .cast::<c_void>();
        call!(
            self.lib,
            rs2_set_devices_changed_callback(self.raw, devices_changed, user)
        )?;
        if let Some(old) = self.callback.replace(state) {
            // librealsense may still run the old callback once; keep it until drop.
            std::mem::forget(old);
        }
        Ok(())
    }

    /// Adds a software device; librealsense then announces it to the callback.
    pub(crate) fn add_software_device(&self, device: &Device) -> Result<(), RsError> {
        call!(
            self.lib,
            rs2_context_add_software_device(self.raw, device.raw)
        )
    }
}

impl Drop for Context {
    fn drop(&mut self) {
        // SAFETY: owned handle, deleted once; the callback state outlives it (dropped
        // with `self.callback` after this).
        unsafe { (self.lib.api.rs2_delete_context)(self.raw) };
    }
}

/// `rs2_device_list`.
pub(crate) struct DeviceList {
    lib: Arc<Lib>,
    raw: *mut RawDeviceList,
}

impl DeviceList {
    /// Number of devices.
    pub(crate) fn len(&self) -> Result<usize, RsError> {
        let n = call!(self.lib, rs2_get_device_count(self.raw))?;
        Ok(usize::try_from(n).unwrap_or(0))
    }

    /// Device `index`.
    pub(crate) fn device(&self, index: usize) -> Result<Device, RsError> {
        let i = c_int::try_from(index).unwrap_or(c_int::MAX);
        let raw = call_ptr!(self.lib, rs2_create_device(self.raw, i))?;
        Ok(Device {
            lib: Arc::clone(&self.lib),
            raw,
        })
    }

    /// True when the list holds `device`.
    pub(crate) fn contains(&self, device: &Device) -> Result<bool, RsError> {
        Ok(call!(self.lib, rs2_device_list_contains(self.raw, device.raw))? != 0)
    }
}

impl Drop for DeviceList {
    fn drop(&mut self) {
        // SAFETY: owned handle, deleted once.
        unsafe { (self.lib.api.rs2_delete_device_list)(self.raw) };
    }
}

/// `rs2_device`.
pub(crate) struct Device {
    lib: Arc<Lib>,
    raw: *mut RawDevice,
}

// SAFETY: librealsense devices are internally synchronised.
unsafe impl Send for Device {}
// SAFETY: as above.
unsafe impl Sync for Device {}

impl Device {
    /// A camera-info string, `None` when the device does not have it.
    pub(crate) fn info(&self, info: CameraInfo) -> Result<Option<String>, RsError> {
        if call!(self.lib, rs2_supports_device_info(self.raw, info as c_int))? == 0 {
            return Ok(None);
        }
        let p = call!(self.lib, rs2_get_device_info(self.raw, info as c_int))?;
        // SAFETY: librealsense returns a string owned by the device, alive while it is.
        Ok(unsafe { text(p) })
    }

    /// The device's sensors.
    pub(crate) fn sensors(&self) -> Result<Vec<Sensor>, RsError> {
        let list = call_ptr!(self.lib, rs2_query_sensors(self.raw))?;
        let result = (|| {
            let n = call!(self.lib, rs2_get_sensors_count(list))?;
            (0..n)
                .map(|i| {
                    call_ptr!(self.lib, rs2_create_sensor(list, i)).map(|raw| Sensor {
                        lib: Arc::clone(&self.lib),
                        raw,
                    })
                })
                .collect()
        })();
        // SAFETY: owned list, deleted once; the sensors are independent handles.
        unsafe { (self.lib.api.rs2_delete_sensor_list)(list) };
        result
    }

    /// True when the device has advanced mode and it is enabled.
    pub(crate) fn advanced_mode_enabled(&self) -> Result<bool, RsError> {
        if call!(
            self.lib,
            rs2_is_device_extendable_to(self.raw, EXTENSION_ADVANCED_MODE)
        )? == 0
        {
            return Ok(false);
        }
        let mut enabled: c_int = 0;
        call!(self.lib, rs2_is_enabled(self.raw, &mut enabled))?;
        Ok(enabled != 0)
    }

    /// Loads an advanced-mode JSON document (`rs2_load_json`).
    pub(crate) fn load_json(&self, json: &str) -> Result<(), RsError> {
        let size = c_uint::try_from(json.len()).map_err(|_| RsError {
            function: "rs2_load_json".to_owned(),
            message: "document larger than 4 GiB".to_owned(),
        })?;
        call!(
            self.lib,
            rs2_load_json(self.raw, json.as_ptr().cast::<c_void>(), size)
        )
    }

    /// The device's advanced-mode JSON document (`rs2_serialize_json`).
    pub(crate) fn serialize_json(&self) -> Result<String, RsError> {
        let buffer = call_ptr!(self.lib, rs2_serialize_json(self.raw))?;
        let result = (|| {
            let data = call!(self.lib, rs2_get_raw_data(buffer))?;
            let size = call!(self.lib, rs2_get_raw_data_size(buffer))?;
            let size = usize::try_from(size).unwrap_or(0);
            if data.is_null() || size == 0 {
                return Ok(String::new());
            }
            // SAFETY: librealsense's buffer holds `size` bytes at `data`, alive until
            // the buffer is deleted below.
            let bytes = unsafe { std::slice::from_raw_parts(data, size) };
            Ok(String::from_utf8_lossy(bytes).into_owned())
        })();
        // SAFETY: owned buffer, deleted once.
        unsafe { (self.lib.api.rs2_delete_raw_data)(buffer) };
        result
    }
}

impl Drop for Device {
    fn drop(&mut self) {
        // SAFETY: owned handle, deleted once.
        unsafe { (self.lib.api.rs2_delete_device)(self.raw) };
    }
}

/// `rs2_sensor`.
pub(crate) struct Sensor {
    lib: Arc<Lib>,
    raw: *mut RawSensor,
}

// SAFETY: librealsense sensors are internally synchronised.
unsafe impl Send for Sensor {}
// SAFETY: as above.
unsafe impl Sync for Sensor {}

impl Sensor {
    /// Every stream profile the sensor offers.
    pub(crate) fn profiles(&self) -> Result<ProfileList, RsError> {
        let raw = call_ptr!(self.lib, rs2_get_stream_profiles(self.raw))?;
        Ok(ProfileList {
            lib: Arc::clone(&self.lib),
            raw,
        })
    }

    /// The profiles the sensor is open with (empty when closed).
    pub(crate) fn active_profiles(&self) -> Result<ProfileList, RsError> {
        let raw = call_ptr!(self.lib, rs2_get_active_streams(self.raw))?;
        Ok(ProfileList {
            lib: Arc::clone(&self.lib),
            raw,
        })
    }

    /// The value of an option (`rs2_get_option` on the sensor's options).
    pub(crate) fn option(&self, option: c_int) -> Result<f32, RsError> {
        call!(
            self.lib,
            rs2_get_option(self.raw.cast::<RawOptions>(), option)
        )
    }

    /// Opens the sensor with one profile.
    pub(crate) fn open(&self, profile: &Profile<'_>) -> Result<(), RsError> {
        call!(self.lib, rs2_open(self.raw, profile.raw))
    }

    /// Starts streaming into `queue`.
    pub(crate) fn start(&self, queue: &FrameQueue) -> Result<(), RsError> {
        call!(self.lib, rs2_start_queue(self.raw, queue.raw))
    }

    /// Stops streaming.
    pub(crate) fn stop(&self) -> Result<(), RsError> {
        call!(self.lib, rs2_stop(self.raw))
    }

    /// Closes the sensor.
    pub(crate) fn close(&self) -> Result<(), RsError> {
        call!(self.lib, rs2_close(self.raw))
    }
}

impl Drop for Sensor {
    fn drop(&mut self) {
        // SAFETY: owned handle, deleted once.
        unsafe { (self.lib.api.rs2_delete_sensor)(self.raw) };
    }
}

/// `rs2_stream_profile_list`.
pub(crate) struct ProfileList {
    lib: Arc<Lib>,
    raw: *mut RawProfileList,
}

impl ProfileList {
    /// Number of profiles.
    pub(crate) fn len(&self) -> Result<usize, RsError> {
        let n = call!(self.lib, rs2_get_stream_profiles_count(self.raw))?;
        Ok(usize::try_from(n).unwrap_or(0))
    }

    /// Profile `index`, borrowed from the list.
    pub(crate) fn get(&self, index: usize) -> Result<Profile<'_>, RsError> {
        let i = c_int::try_from(index).unwrap_or(c_int::MAX);
        let raw = call!(self.lib, rs2_get_stream_profile(self.raw, i))?;
        let raw = self
            .lib
            .non_null("rs2_get_stream_profile", raw.cast_mut())?;
        Ok(Profile {
            lib: &self.lib,
            raw,
            _owner: PhantomData,
        })
    }
}

impl Drop for ProfileList {
    fn drop(&mut self) {
        // SAFETY: owned handle, deleted once.
        unsafe { (self.lib.api.rs2_delete_stream_profiles_list)(self.raw) };
    }
}

/// What a stream profile describes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct ProfileData {
    /// `rs2_stream`.
    pub(crate) stream: c_int,
    /// `rs2_format`.
    pub(crate) format: c_int,
    /// Unique id of the profile.
    pub(crate) uid: c_int,
    /// Frames per second.
    pub(crate) fps: c_int,
    /// Width in pixels (0 for non-video profiles).
    pub(crate) width: c_int,
    /// Height in pixels.
    pub(crate) height: c_int,
}

/// A stream profile borrowed from its owner (a list, a frame or a software sensor).
#[derive(Clone, Copy)]
pub(crate) struct Profile<'a> {
    lib: &'a Lib,
    raw: *mut RawProfile,
    _owner: PhantomData<&'a RawProfile>,
}

impl Profile<'_> {
    /// Stream, format, unique id, frame rate and resolution.
    pub(crate) fn data(&self) -> Result<ProfileData, RsError> {
        let (mut stream, mut format, mut index, mut uid, mut fps) = (0, 0, 0, 0, 0);
        call!(
            self.lib,
            rs2_get_stream_profile_data(
                self.raw,
                &mut stream,
                &mut format,
                &mut index,
                &mut uid,
                &mut fps
            )
        )?;
        let (mut width, mut height) = (0, 0);
        call!(
            self.lib,
            rs2_get_video_stream_resolution(self.raw, &mut width, &mut height)
        )?;
        Ok(ProfileData {
            stream,
            format,
            uid,
            fps,
            width,
            height,
        })
    }

    /// The video stream's intrinsics.
    pub(crate) fn intrinsics(&self) -> Result<RsIntrinsics, RsError> {
        let mut k = RsIntrinsics::default();
        call!(self.lib, rs2_get_video_stream_intrinsics(self.raw, &mut k))?;
        Ok(k)
    }

    /// The transform from this profile's stream to `to`'s.
    pub(crate) fn extrinsics_to(&self, to: &Profile<'_>) -> Result<RsExtrinsics, RsError> {
        let mut e = RsExtrinsics::default();
        call!(self.lib, rs2_get_extrinsics(self.raw, to.raw, &mut e))?;
        Ok(e)
    }

    /// Tells librealsense the transform from this profile's stream to `to`'s.
    pub(crate) fn register_extrinsics(
        &self,
        to: &Profile<'_>,
        e: RsExtrinsics,
    ) -> Result<(), RsError> {
        call!(self.lib, rs2_register_extrinsics(self.raw, to.raw, e))
    }
}

/// `rs2_frame_queue`.
pub(crate) struct FrameQueue {
    lib: Arc<Lib>,
    raw: *mut RawFrameQueue,
}

// SAFETY: librealsense frame queues are thread-safe.
unsafe impl Send for FrameQueue {}
// SAFETY: as above.
unsafe impl Sync for FrameQueue {}

impl FrameQueue {
    /// A queue holding at most `capacity` frames (older ones are dropped).
    pub(crate) fn new(lib: &Arc<Lib>, capacity: u16) -> Result<Self, RsError> {
        let raw = call_ptr!(lib, rs2_create_frame_queue(c_int::from(capacity)))?;
        Ok(Self {
            lib: Arc::clone(lib),
            raw,
        })
    }

    /// Waits at most `timeout_ms` for a frame; `None` on timeout.
    pub(crate) fn wait(&self, timeout_ms: u32) -> Result<Option<Frame>, RsError> {
        let mut frame: *mut RawFrame = ptr::null_mut();
        let got = call!(
            self.lib,
            rs2_try_wait_for_frame(self.raw, timeout_ms, &mut frame)
        )?;
        Ok(self.frame(got, frame))
    }

    /// A frame if one is queued, without waiting.
    pub(crate) fn poll(&self) -> Result<Option<Frame>, RsError> {
        let mut frame: *mut RawFrame = ptr::null_mut();
        let got = call!(self.lib, rs2_poll_for_frame(self.raw, &mut frame))?;
        Ok(self.frame(got, frame))
    }

    fn frame(&self, got: c_int, raw: *mut RawFrame) -> Option<Frame> {
        (got != 0 && !raw.is_null()).then(|| Frame {
            lib: Arc::clone(&self.lib),
            raw,
        })
    }
}

impl Drop for FrameQueue {
    fn drop(&mut self) {
        // SAFETY: owned handle, deleted once.
        unsafe { (self.lib.api.rs2_delete_frame_queue)(self.raw) };
    }
}

/// `rs2_frame` (a video frame).
pub(crate) struct Frame {
    lib: Arc<Lib>,
    raw: *mut RawFrame,
}

// SAFETY: frames are reference-counted and immutable once published.
unsafe impl Send for Frame {}

impl Frame {
    /// The frame's pixels. Frames of a software device report a data size of 0
    /// (librealsense keeps the injected buffer outside the frame); their size is then
    /// stride * height, the buffer the injector handed over.
    pub(crate) fn data(&self) -> Result<&[u8], RsError> {
        let p = call!(self.lib, rs2_get_frame_data(self.raw))?;
        let size = match call!(self.lib, rs2_get_frame_data_size(self.raw))? {
            0 => {
                let (_, height, stride) = self.geometry()?;
                i64::from(height) * i64::from(stride)
            }
            n => i64::from(n),
        };
        let size = usize::try_from(size).unwrap_or(0);
        if p.is_null() || size == 0 {
            return Ok(&[]);
        }
        // SAFETY: librealsense keeps `size` bytes at `p` until the frame is released,
        // which needs `self`.
        Ok(unsafe { std::slice::from_raw_parts(p.cast::<u8>(), size) })
    }

    /// The frame's capture time on the host's clock, µs since the UNIX epoch, when
    /// librealsense gives it in a host domain: global time (the camera's clock mapped
    /// onto the host's, D400 cameras with frame metadata) or system time (the host's
    /// clock at the frame's arrival). `None` for the camera's own clock (no metadata, or
    /// a software device), which no other host shares.
    pub(crate) fn host_time_us(&self) -> Result<Option<u64>, RsError> {
        let domain = call!(self.lib, rs2_get_frame_timestamp_domain(self.raw))?;
        if domain != TIMESTAMP_DOMAIN_GLOBAL_TIME && domain != TIMESTAMP_DOMAIN_SYSTEM_TIME {
            return Ok(None);
        }
        let ms = call!(self.lib, rs2_get_frame_timestamp(self.raw))?;
        Ok((ms.is_finite() && ms > 0.0).then(|| (ms * 1e3).round() as u64))
    }

    /// Width and height in pixels, and bytes per row.
    pub(crate) fn geometry(&self) -> Result<(i32, i32, i32), RsError> {
        Ok((
            call!(self.lib, rs2_get_frame_width(self.raw))?,
            call!(self.lib, rs2_get_frame_height(self.raw))?,
            call!(self.lib, rs2_get_frame_stride_in_bytes(self.raw))?,
        ))
    }

    /// The profile the frame was captured with.
    pub(crate) fn profile(&self) -> Result<Profile<'_>, RsError> {
        let raw = call!(self.lib, rs2_get_frame_stream_profile(self.raw))?;
        let raw = self
            .lib
            .non_null("rs2_get_frame_stream_profile", raw.cast_mut())?;
        Ok(Profile {
            lib: &self.lib,
            raw,
            _owner: PhantomData,
        })
    }
}

impl Drop for Frame {
    fn drop(&mut self) {
        // SAFETY: owned reference, released once.
        unsafe { (self.lib.api.rs2_release_frame)(self.raw) };
    }
}

/// Pixel buffers handed to software sensors, by address, until librealsense calls
/// [`release_pixels`]. Words of 8 bytes keep 16-bit depth aligned.
static PIXELS: Mutex<BTreeMap<usize, Box<[u64]>>> = Mutex::new(BTreeMap::new());

extern "C" fn release_pixels(pixels: *mut c_void) {
    // The map is consistent whatever a panicking holder did: single inserts/removes.
    let mut map = PIXELS.lock().unwrap_or_else(PoisonError::into_inner);
    map.remove(&(pixels as usize));
}

/// A software device (`rs_internal.h`): a camera whose frames the caller injects.
pub(crate) struct SoftwareDevice {
    device: Device,
}

impl SoftwareDevice {
    /// An empty software device.
    pub(crate) fn new(lib: &Arc<Lib>) -> Result<Self, RsError> {
        let raw = call_ptr!(lib, rs2_create_software_device())?;
        Ok(Self {
            device: Device {
                lib: Arc::clone(lib),
                raw,
            },
        })
    }

    /// The device handle (to add to a context).
    pub(crate) fn device(&self) -> &Device {
        &self.device
    }

    /// Registers a camera-info string.
    pub(crate) fn register_info(&self, info: CameraInfo, value: &str) -> Result<(), RsError> {
        let value = c_string("rs2_software_device_register_info", value)?;
        call!(
            self.device.lib,
            rs2_software_device_register_info(self.device.raw, info as c_int, value.as_ptr())
        )
    }

    /// Adds a sensor.
    pub(crate) fn add_sensor(&self, name: &str) -> Result<SoftwareSensor, RsError> {
        let name = c_string("rs2_software_device_add_sensor", name)?;
        let raw = call_ptr!(
            self.device.lib,
            rs2_software_device_add_sensor(self.device.raw, name.as_ptr())
        )?;
        Ok(SoftwareSensor {
            sensor: Sensor {
                lib: Arc::clone(&self.device.lib),
                raw,
            },
            profiles: Vec::new(),
        })
    }
}

/// A sensor of a software device and the profiles added to it.
pub(crate) struct SoftwareSensor {
    sensor: Sensor,
    profiles: Vec<*mut RawProfile>,
}

// SAFETY: the profiles are owned by the sensor, which librealsense synchronises.
unsafe impl Send for SoftwareSensor {}
// SAFETY: as above.
unsafe impl Sync for SoftwareSensor {}

impl SoftwareSensor {
    /// The sensor.
    pub(crate) fn sensor(&self) -> &Sensor {
        &self.sensor
    }

    /// Adds a video stream profile; returns its index in [`SoftwareSensor::profile`].
    pub(crate) fn add_video_stream(&mut self, stream: RsVideoStream) -> Result<usize, RsError> {
        let raw = call_ptr!(
            self.sensor.lib,
            rs2_software_sensor_add_video_stream(self.sensor.raw, stream)
        )?;
        self.profiles.push(raw);
        Ok(self.profiles.len() - 1)
    }

    /// Profile `index` of the added ones.
    pub(crate) fn profile(&self, index: usize) -> Option<Profile<'_>> {
        self.profiles.get(index).map(|&raw| Profile {
            lib: &self.sensor.lib,
            raw,
            _owner: PhantomData,
        })
    }

    /// Number of profiles added.
    pub(crate) fn profile_count(&self) -> usize {
        self.profiles.len()
    }

    /// Adds a read-only option with its value.
    pub(crate) fn add_read_only_option(&self, option: c_int, value: f32) -> Result<(), RsError> {
        call!(
            self.sensor.lib,
            rs2_software_sensor_add_read_only_option(self.sensor.raw, option, value)
        )
    }

    /// Injects one video frame of added profile `index` (`bytes` rows of `stride`
    /// bytes, `bpp` bytes per pixel). librealsense drops it unless the sensor is
    /// streaming.
    pub(crate) fn inject(&self, index: usize, frame: &InjectedFrame<'_>) -> Result<(), RsError> {
        let function = "rs2_software_sensor_on_video_frame";
        let profile = *self.profiles.get(index).ok_or_else(|| RsError {
            function: function.to_owned(),
            message: format!("no profile {index}"),
        })?;
        let invalid = |what: &str| RsError {
            function: function.to_owned(),
            message: format!("{what} out of range"),
        };
        let stride = c_int::try_from(frame.stride).map_err(|_| invalid("stride"))?;
        let bpp = c_int::try_from(frame.bpp).map_err(|_| invalid("bpp"))?;
        let number = c_int::try_from(frame.number % (c_int::MAX as u64)).unwrap_or(0);
        let mut words = vec![0u64; frame.bytes.len().div_ceil(8)].into_boxed_slice();
        for (word, chunk) in words.iter_mut().zip(frame.bytes.chunks(8)) {
            let mut b = [0u8; 8];
            b[..chunk.len()].copy_from_slice(chunk);
            *word = u64::from_ne_bytes(b);
        }
        let pixels = words.as_mut_ptr().cast::<c_void>();
        PIXELS
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(pixels as usize, words);
        let raw = RsSoftwareVideoFrame {
            pixels,
            deleter: release_pixels,
            stride,
            bpp,
            timestamp_ms: frame.timestamp_ms,
            domain: TIMESTAMP_DOMAIN_HARDWARE_CLOCK,
            frame_number: number,
            profile,
            depth_units: frame.depth_units,
        };
        // On an error the buffer stays registered: librealsense may still own it.
        call!(
            self.sensor.lib,
            rs2_software_sensor_on_video_frame(self.sensor.raw, raw)
        )
    }
}

/// One frame for [`SoftwareSensor::inject`].
#[derive(Debug)]
pub(crate) struct InjectedFrame<'a> {
    /// Pixels, `stride * height` bytes.
    pub(crate) bytes: &'a [u8],
    /// Bytes per row.
    pub(crate) stride: usize,
    /// Bytes per pixel.
    pub(crate) bpp: usize,
    /// Frame counter.
    pub(crate) number: u64,
    /// Device timestamp in milliseconds.
    pub(crate) timestamp_ms: f64,
    /// Metres per depth unit (ignored for color).
    pub(crate) depth_units: f32,
}
