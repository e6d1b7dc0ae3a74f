package android.hardware.camera2;

import android.hardware.camera2.params.SessionConfiguration;

public abstract class CameraDevice implements AutoCloseable {
    public static final int TEMPLATE_PREVIEW = 1;
    public static final int TEMPLATE_STILL_CAPTURE = 2;

    CameraDevice() {
        throw new RuntimeException("Stub!");
    }

    public abstract String getId();

    public abstract CaptureRequest.Builder createCaptureRequest(int templateType) throws CameraAccessException;

    public void createCaptureSession(SessionConfiguration config) throws CameraAccessException {
        throw new RuntimeException("Stub!");
    }

    @Override
    public abstract void close();

    public abstract static class StateCallback {
        public static final int ERROR_CAMERA_IN_USE = 1;
        public static final int ERROR_MAX_CAMERAS_IN_USE = 2;
        public static final int ERROR_CAMERA_DISABLED = 3;
        public static final int ERROR_CAMERA_DEVICE = 4;
        public static final int ERROR_CAMERA_SERVICE = 5;

        public StateCallback() {
            throw new RuntimeException("Stub!");
        }

        public abstract void onOpened(CameraDevice camera);

        public void onClosed(CameraDevice camera) {
            throw new RuntimeException("Stub!");
        }

        public abstract void onDisconnected(CameraDevice camera);

        public abstract void onError(CameraDevice camera, int error);
    }
}
