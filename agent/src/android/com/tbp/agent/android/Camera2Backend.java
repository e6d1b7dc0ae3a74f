package com.tbp.agent.android;

import android.hardware.camera2.CameraAccessException;
import android.hardware.camera2.CameraCaptureSession;
import android.hardware.camera2.CameraDevice;
import android.hardware.camera2.CameraManager;
import android.hardware.camera2.CaptureFailure;
import android.hardware.camera2.CaptureRequest;
import android.hardware.camera2.CaptureResult;
import android.hardware.camera2.TotalCaptureResult;
import android.hardware.camera2.params.OutputConfiguration;
import android.hardware.camera2.params.SessionConfiguration;
import android.media.Image;
import android.media.ImageReader;
import android.os.Handler;
import android.os.HandlerThread;
import android.os.SystemClock;
import com.tbp.agent.CameraBackend;
import com.tbp.agent.ErrorCode;
import com.tbp.agent.Log;
import java.nio.ByteBuffer;
import java.util.ArrayDeque;
import java.util.Arrays;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.Executor;
import java.util.concurrent.TimeUnit;

/**
 * The agent's camera on a phone, through Camera2. One capture session with two outputs: a small
 * YUV stream under a repeating request (AF, AE and flash off, manual exposure and sensitivity,
 * LENS_FOCUS_DISTANCE in diopters), whose results report the lens, and a JPEG ImageReader at the
 * full size for stills (TEMPLATE_STILL_CAPTURE with the same manual settings). Everything runs on
 * one camera thread; the core's calls are posted to it.
 *
 * <p>focus answers once a result of the repeating request carrying the new distance reports
 * LENS_STATE STATIONARY at that distance (within {@value #FOCUS_TOLERANCE_DIOPTERS} D + 1 %), or
 * FOCUS_TIMEOUT after {@value #FOCUS_TIMEOUT_MS} ms. capture answers once both the capture result
 * (SENSOR_TIMESTAMP, SENSOR_EXPOSURE_TIME, LENS_FOCUS_DISTANCE) and its JPEG (the image with that
 * timestamp) have arrived. A camera that disconnects or errors fails the operation in flight and
 * every later one with CAMERA_ERROR (CAMERA_BUSY when another client holds it); the controller's
 * reconnect starts a new agent, which opens the camera again.
 */
final class Camera2Backend implements CameraBackend {

    static final long OPEN_TIMEOUT_MS = 5000;
    static final long FOCUS_TIMEOUT_MS = 1000;
    static final long CAPTURE_TIMEOUT_MS = 5000;
    static final double FOCUS_TOLERANCE_DIOPTERS = 0.02;
    static final byte JPEG_QUALITY = 95;

    private final Camera2Config config;
    private final Log log;
    private final HandlerThread thread = new HandlerThread("camera");
    private final Handler handler;
    private final CountDownLatch ready = new CountDownLatch(1);
    private final ImageReader jpeg;
    private final ImageReader preview;

    // Camera thread only (and the opening thread before `ready`).
    private CameraDevice device;
    private CameraCaptureSession session;
    private CaptureRequest.Builder repeating;
    private double lensDiopters;
    private Focusing focusing;
    private Capturing capturing;
    private ErrorCode lostCode;
    private String lostReason;
    private boolean closed;

    private Camera2Backend(Camera2Config config, Log log) {
        this.config = config;
        this.log = log;
        thread.start();
        handler = new Handler(thread.getLooper());
        jpeg = ImageReader.newInstance(config.jpegSize.getWidth(), config.jpegSize.getHeight(),
                android.graphics.ImageFormat.JPEG, 2);
        preview = ImageReader.newInstance(config.previewSize.getWidth(), config.previewSize.getHeight(),
                android.graphics.ImageFormat.YUV_420_888, 2);
        jpeg.setOnImageAvailableListener(new ImageReader.OnImageAvailableListener() {
            @Override
            public void onImageAvailable(ImageReader reader) {
                onJpeg(reader);
            }
        }, handler);
        preview.setOnImageAvailableListener(new ImageReader.OnImageAvailableListener() {
            @Override
            public void onImageAvailable(ImageReader reader) {
                Image image = reader.acquireLatestImage();
                if (image != null) {
                    image.close();
                }
            }
        }, handler);
    }

    /** Opens the camera and starts its repeating request; the exception's message says why not. */
    static Camera2Backend open(CameraManager manager, Camera2Config config, Log log) throws Exception {
        Camera2Backend backend = new Camera2Backend(config, log);
        try {
            manager.openCamera(config.cameraId, backend.deviceCallback, backend.handler);
            if (!backend.ready.await(OPEN_TIMEOUT_MS, TimeUnit.MILLISECONDS)) {
                throw new Exception("camera " + config.cameraId + " not streaming within " + OPEN_TIMEOUT_MS + " ms");
            }
            if (backend.lostCode != null) {
                throw new Exception(backend.lostReason);
            }
        } catch (Exception e) {
            backend.close();
            throw e;
        }
        log.info("camera " + config.cameraId + " open: JPEG " + config.jpegSize.getWidth() + "x"
                + config.jpegSize.getHeight() + ", min focus " + config.info.minFocusDiopters + " D");
        return backend;
    }

    @Override
    public Info info() {
        return config.info;
    }

    // ------------------------------------------------------------------ the device and the session

    private final CameraDevice.StateCallback deviceCallback = new CameraDevice.StateCallback() {
        @Override
        public void onOpened(CameraDevice camera) {
            device = camera;
            if (closed) {
                camera.close();
                return;
            }
            Executor onCameraThread = new Executor() {
                @Override
                public void execute(Runnable command) {
                    handler.post(command);
                }
            };
            try {
                camera.createCaptureSession(new SessionConfiguration(SessionConfiguration.SESSION_REGULAR,
                        Arrays.asList(new OutputConfiguration(preview.getSurface()),
                                new OutputConfiguration(jpeg.getSurface())), onCameraThread, sessionCallback));
            } catch (CameraAccessException | RuntimeException e) {
                lost(code(e), "createCaptureSession: " + e);
            }
        }

        @Override
        public void onDisconnected(CameraDevice camera) {
            lost(ErrorCode.CAMERA_ERROR, "camera " + config.cameraId
                    + " disconnected (another client took it, or the camera service restarted)");
            camera.close();
        }

        @Override
        public void onError(CameraDevice camera, int error) {
            boolean busy = error == ERROR_CAMERA_IN_USE || error == ERROR_MAX_CAMERAS_IN_USE;
            lost(busy ? ErrorCode.CAMERA_BUSY : ErrorCode.CAMERA_ERROR, "camera " + config.cameraId + " error "
                    + deviceError(error));
            camera.close();
        }
    };

    private final CameraCaptureSession.StateCallback sessionCallback = new CameraCaptureSession.StateCallback() {
        @Override
        public void onConfigured(CameraCaptureSession configured) {
            session = configured;
            try {
                repeating = device.createCaptureRequest(CameraDevice.TEMPLATE_PREVIEW);
                repeating.addTarget(preview.getSurface());
                manual(repeating, lensDiopters, config.info.exposureS, config.info.iso);
                repeating.setTag(new Object());
                session.setRepeatingRequest(repeating.build(), lensCallback, handler);
            } catch (CameraAccessException | RuntimeException e) {
                lost(code(e), "the repeating request: " + e);
                return;
            }
            ready.countDown();
        }

        @Override
        public void onConfigureFailed(CameraCaptureSession failed) {
            lost(ErrorCode.CAMERA_ERROR, "camera " + config.cameraId + ": capture session configuration failed");
        }
    };

    /** AF, AE and flash off; the lens, exposure and sensitivity as given; white balance automatic. */
    private static void manual(CaptureRequest.Builder request, double diopters, double exposureS, long iso) {
        request.set(CaptureRequest.CONTROL_MODE, CaptureRequest.CONTROL_MODE_AUTO);
        request.set(CaptureRequest.CONTROL_AF_MODE, CaptureRequest.CONTROL_AF_MODE_OFF);
        request.set(CaptureRequest.CONTROL_AE_MODE, CaptureRequest.CONTROL_AE_MODE_OFF);
        request.set(CaptureRequest.CONTROL_AWB_MODE, CaptureRequest.CONTROL_AWB_MODE_AUTO);
        request.set(CaptureRequest.FLASH_MODE, CaptureRequest.FLASH_MODE_OFF);
        request.set(CaptureRequest.LENS_FOCUS_DISTANCE, (float) diopters);
        request.set(CaptureRequest.SENSOR_EXPOSURE_TIME, Math.round(exposureS * 1e9));
        request.set(CaptureRequest.SENSOR_SENSITIVITY, (int) iso);
    }

    /** The camera is gone or failed: the waiting opener, the operation in flight and later ones are told. */
    private void lost(ErrorCode code, String reason) {
        if (lostCode == null) {
            lostCode = code;
            lostReason = reason;
            log.info(reason);
        }
        if (focusing != null) {
            Focusing f = focusing;
            focusing = null;
            handler.removeCallbacks(f.timeout);
            f.result.failed(code, reason);
        }
        if (capturing != null) {
            failCapture(code, reason);
        }
        ready.countDown();
    }

    private static ErrorCode code(Exception e) {
        if (e instanceof CameraAccessException) {
            int reason = ((CameraAccessException) e).getReason();
            if (reason == CameraAccessException.CAMERA_IN_USE || reason == CameraAccessException.MAX_CAMERAS_IN_USE) {
                return ErrorCode.CAMERA_BUSY;
            }
        }
        return ErrorCode.CAMERA_ERROR;
    }

    private static String deviceError(int error) {
        switch (error) {
            case CameraDevice.StateCallback.ERROR_CAMERA_IN_USE:
                return "ERROR_CAMERA_IN_USE";
            case CameraDevice.StateCallback.ERROR_MAX_CAMERAS_IN_USE:
                return "ERROR_MAX_CAMERAS_IN_USE";
            case CameraDevice.StateCallback.ERROR_CAMERA_DISABLED:
                return "ERROR_CAMERA_DISABLED (device policy, or a background client before Android 12)";
            case CameraDevice.StateCallback.ERROR_CAMERA_DEVICE:
                return "ERROR_CAMERA_DEVICE";
            case CameraDevice.StateCallback.ERROR_CAMERA_SERVICE:
                return "ERROR_CAMERA_SERVICE";
            default:
                return String.valueOf(error);
        }
    }

    // ------------------------------------------------------------------ focus

    /** A focus waiting for its stationary result. */
    private final class Focusing {
        final double target;
        final Object tag;
        final Result<Focused> result;
        Integer lastState;
        Float lastDistance;
        final Runnable timeout = new Runnable() {
            @Override
            public void run() {
                if (focusing == Focusing.this) {
                    focusing = null;
                    result.failed(ErrorCode.FOCUS_TIMEOUT, "lens not stationary at " + target + " D within "
                            + FOCUS_TIMEOUT_MS + " ms (last result: LENS_STATE " + lastState + ", LENS_FOCUS_DISTANCE "
                            + lastDistance + ")");
                }
            }
        };

        Focusing(double target, Object tag, Result<Focused> result) {
            this.target = target;
            this.tag = tag;
            this.result = result;
        }
    }

    @Override
    public void focus(final double diopters, final Result<Focused> result) {
        post(result, new Runnable() {
            @Override
            public void run() {
                Object tag = new Object();
                repeating.set(CaptureRequest.LENS_FOCUS_DISTANCE, (float) diopters);
                repeating.setTag(tag);
                try {
                    session.setRepeatingRequest(repeating.build(), lensCallback, handler);
                } catch (CameraAccessException | RuntimeException e) {
                    result.failed(code(e), "setRepeatingRequest: " + e);
                    return;
                }
                lensDiopters = diopters;
                focusing = new Focusing(diopters, tag, result);
                handler.postDelayed(focusing.timeout, FOCUS_TIMEOUT_MS);
            }
        });
    }

    private final CameraCaptureSession.CaptureCallback lensCallback = new CameraCaptureSession.CaptureCallback() {
        @Override
        public void onCaptureCompleted(CameraCaptureSession s, CaptureRequest request, TotalCaptureResult result) {
            Focusing f = focusing;
            if (f == null || request.getTag() != f.tag) {
                return;
            }
            Integer state = result.get(CaptureResult.LENS_STATE);
            Float distance = result.get(CaptureResult.LENS_FOCUS_DISTANCE);
            Long timestamp = result.get(CaptureResult.SENSOR_TIMESTAMP);
            f.lastState = state;
            f.lastDistance = distance;
            if (state == null || state != CaptureResult.LENS_STATE_STATIONARY || distance == null || timestamp == null
                    || Math.abs(distance - f.target) > FOCUS_TOLERANCE_DIOPTERS + 0.01 * f.target) {
                return;
            }
            focusing = null;
            handler.removeCallbacks(f.timeout);
            f.result.ok(new Focused(distance, timestamp));
        }
    };

    // ------------------------------------------------------------------ capture

    /** A still waiting for its capture result and its JPEG. */
    private final class Capturing {
        final Object tag;
        final Result<Still> result;
        Long timestampNs;
        long exposureNs;
        double focusDiopters;
        /** JPEGs that arrived while this capture waits: its own, maybe a failed one's late image. */
        final ArrayDeque<Image> images = new ArrayDeque<>();
        final Runnable timeout = new Runnable() {
            @Override
            public void run() {
                if (capturing == Capturing.this) {
                    failCapture(ErrorCode.CAMERA_ERROR, "no capture result and JPEG within " + CAPTURE_TIMEOUT_MS
                            + " ms (result " + (timestampNs != null) + ", images " + images.size() + ")");
                }
            }
        };

        Capturing(Object tag, Result<Still> result) {
            this.tag = tag;
            this.result = result;
        }
    }

    @Override
    public void capture(final double exposureS, final long iso, final Result<Still> result) {
        post(result, new Runnable() {
            @Override
            public void run() {
                Object tag = new Object();
                try {
                    CaptureRequest.Builder still = device.createCaptureRequest(CameraDevice.TEMPLATE_STILL_CAPTURE);
                    still.addTarget(jpeg.getSurface());
                    manual(still, lensDiopters, exposureS, iso);
                    still.set(CaptureRequest.JPEG_QUALITY, JPEG_QUALITY);
                    still.set(CaptureRequest.JPEG_ORIENTATION, 0);
                    still.setTag(tag);
                    capturing = new Capturing(tag, result);
                    session.capture(still.build(), stillCallback, handler);
                } catch (CameraAccessException | RuntimeException e) {
                    capturing = null;
                    result.failed(code(e), "capture: " + e);
                    return;
                }
                handler.postDelayed(capturing.timeout, CAPTURE_TIMEOUT_MS);
            }
        });
    }

    private final CameraCaptureSession.CaptureCallback stillCallback = new CameraCaptureSession.CaptureCallback() {
        @Override
        public void onCaptureCompleted(CameraCaptureSession s, CaptureRequest request, TotalCaptureResult result) {
            Capturing c = capturing;
            if (c == null || request.getTag() != c.tag) {
                return;
            }
            Long timestamp = result.get(CaptureResult.SENSOR_TIMESTAMP);
            Long exposure = result.get(CaptureResult.SENSOR_EXPOSURE_TIME);
            Float focus = result.get(CaptureResult.LENS_FOCUS_DISTANCE);
            if (timestamp == null || exposure == null || focus == null) {
                failCapture(ErrorCode.CAPTURE_FAILED, "the capture result lacks SENSOR_TIMESTAMP, SENSOR_EXPOSURE_TIME"
                        + " or LENS_FOCUS_DISTANCE");
                return;
            }
            c.timestampNs = timestamp;
            c.exposureNs = exposure;
            c.focusDiopters = focus;
            deliver(c);
        }

        @Override
        public void onCaptureFailed(CameraCaptureSession s, CaptureRequest request, CaptureFailure failure) {
            Capturing c = capturing;
            if (c != null && request.getTag() == c.tag) {
                failCapture(ErrorCode.CAPTURE_FAILED, "onCaptureFailed reason " + failure.getReason()
                        + (failure.wasImageCaptured() ? " (an image was captured)" : ""));
            }
        }
    };

    private void onJpeg(ImageReader reader) {
        Image image;
        try {
            image = reader.acquireNextImage();
        } catch (IllegalStateException full) {  // every buffer held: wait for one to be released
            log.error("JPEG reader", full);
            return;
        }
        if (image == null) {
            return;
        }
        Capturing c = capturing;
        if (c == null) {  // a failed or timed-out capture's late image
            image.close();
            return;
        }
        c.images.add(image);
        if (c.images.size() > 1 && c.timestampNs == null) {  // keep one buffer free for the next image
            c.images.poll().close();
        }
        deliver(c);
    }

    /** Hands the still over once its result and its image (the one with its timestamp) are both here. */
    private void deliver(Capturing c) {
        if (c.timestampNs == null) {
            return;
        }
        Image image = null;
        for (Image candidate : c.images) {
            if (candidate.getTimestamp() == c.timestampNs) {
                image = candidate;
            }
        }
        for (Image other : c.images) {  // images of earlier, failed captures
            if (other != image) {
                other.close();
            }
        }
        c.images.clear();
        if (image == null) {
            return;
        }
        capturing = null;
        handler.removeCallbacks(c.timeout);
        final Image jpegImage = image;
        final ByteBuffer bytes = jpegImage.getPlanes()[0].getBuffer();
        c.result.ok(new Still(c.timestampNs, c.exposureNs / 1e9, c.focusDiopters) {
            private boolean released;

            @Override
            public ByteBuffer jpeg() {
                return bytes;
            }

            @Override
            public synchronized void release() {
                if (!released) {
                    released = true;
                    jpegImage.close();
                }
            }
        });
    }

    private void failCapture(ErrorCode code, String reason) {
        Capturing c = capturing;
        capturing = null;
        handler.removeCallbacks(c.timeout);
        for (Image image : c.images) {
            image.close();
        }
        c.result.failed(code, reason);
    }

    // ------------------------------------------------------------------ clock and life

    /** SENSOR_TIMESTAMP's clock: CLOCK_BOOTTIME for the realtime source; else CLOCK_MONOTONIC, the
     *  base Camera2 documents as roughly that of an unknown source. Read at once, on the caller's thread. */
    @Override
    public void readClock(Result<Long> result) {
        result.ok(config.realtimeClock ? SystemClock.elapsedRealtimeNanos() : System.nanoTime());
    }

    /** Runs an operation on the camera thread, unless the camera is lost or closed. */
    private void post(final Result<?> result, final Runnable operation) {
        boolean posted = handler.post(new Runnable() {
            @Override
            public void run() {
                if (closed) {
                    result.failed(ErrorCode.CAMERA_ERROR, "the camera is closed");
                } else if (lostCode != null) {
                    result.failed(lostCode, lostReason);
                } else {
                    operation.run();
                }
            }
        });
        if (!posted) {
            result.failed(ErrorCode.CAMERA_ERROR, "the camera thread has ended");
        }
    }

    @Override
    public void close() {
        handler.post(new Runnable() {
            @Override
            public void run() {
                closed = true;
                if (session != null) {
                    session.close();
                }
                if (device != null) {
                    device.close();
                }
                jpeg.close();
                preview.close();
            }
        });
        thread.quitSafely();
    }
}
