package android.hardware.camera2;

import android.os.Handler;

public final class CameraManager {
    private CameraManager() {
        throw new RuntimeException("Stub!");
    }

    public String[] getCameraIdList() throws CameraAccessException {
        throw new RuntimeException("Stub!");
    }

    public CameraCharacteristics getCameraCharacteristics(String cameraId) throws CameraAccessException {
        throw new RuntimeException("Stub!");
    }

    public void openCamera(String cameraId, CameraDevice.StateCallback callback, Handler handler)
            throws CameraAccessException {
        throw new RuntimeException("Stub!");
    }
}
