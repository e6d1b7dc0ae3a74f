package android.hardware.camera2;

import android.view.Surface;

public final class CaptureRequest extends CameraMetadata<CaptureRequest.Key<?>> {
    public static final Key<Integer> CONTROL_AE_MODE = null;
    public static final Key<Integer> CONTROL_AF_MODE = null;
    public static final Key<Integer> CONTROL_AWB_MODE = null;
    public static final Key<Integer> CONTROL_MODE = null;
    public static final Key<Integer> FLASH_MODE = null;
    public static final Key<Integer> JPEG_ORIENTATION = null;
    public static final Key<Byte> JPEG_QUALITY = null;
    public static final Key<Float> LENS_FOCUS_DISTANCE = null;
    public static final Key<Long> SENSOR_EXPOSURE_TIME = null;
    public static final Key<Integer> SENSOR_SENSITIVITY = null;

    private CaptureRequest() {
        throw new RuntimeException("Stub!");
    }

    public Object getTag() {
        throw new RuntimeException("Stub!");
    }

    public static final class Key<T> {
        private Key() {
            throw new RuntimeException("Stub!");
        }
    }

    public static final class Builder {
        private Builder() {
            throw new RuntimeException("Stub!");
        }

        public void addTarget(Surface outputTarget) {
            throw new RuntimeException("Stub!");
        }

        public <T> void set(Key<T> key, T value) {
            throw new RuntimeException("Stub!");
        }

        public void setTag(Object tag) {
            throw new RuntimeException("Stub!");
        }

        public CaptureRequest build() {
            throw new RuntimeException("Stub!");
        }
    }
}
