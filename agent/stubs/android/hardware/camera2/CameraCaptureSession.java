package android.hardware.camera2;

import android.os.Handler;

public abstract class CameraCaptureSession implements AutoCloseable {
    public CameraCaptureSession() {
        throw new RuntimeException("Stub!");
    }

    public abstract int capture(CaptureRequest request, CaptureCallback listener, Handler handler)
            throws CameraAccessException;

    public abstract int setRepeatingRequest(CaptureRequest request, CaptureCallback listener, Handler handler)
            throws CameraAccessException;

    @Override
    public abstract void close();

    public abstract static class StateCallback {
        public StateCallback() {
            throw new RuntimeException("Stub!");
        }

        public abstract void onConfigured(CameraCaptureSession session);

        public abstract void onConfigureFailed(CameraCaptureSession session);
    }

    public abstract static class CaptureCallback {
        public CaptureCallback() {
            throw new RuntimeException("Stub!");
        }

        public void onCaptureCompleted(CameraCaptureSession session, CaptureRequest request, TotalCaptureResult result) {
            throw new RuntimeException("Stub!");
        }

        public void onCaptureFailed(CameraCaptureSession session, CaptureRequest request, CaptureFailure failure) {
            throw new RuntimeException("Stub!");
        }
    }
}
