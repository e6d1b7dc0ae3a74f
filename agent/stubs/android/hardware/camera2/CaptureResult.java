package android.hardware.camera2;

public class CaptureResult extends CameraMetadata<CaptureResult.Key<?>> {
    public static final Key<Float> LENS_FOCUS_DISTANCE = null;
    public static final Key<Integer> LENS_STATE = null;
    public static final Key<Long> SENSOR_EXPOSURE_TIME = null;
    public static final Key<Long> SENSOR_TIMESTAMP = null;

    CaptureResult() {
        throw new RuntimeException("Stub!");
    }

    public <T> T get(Key<T> key) {
        throw new RuntimeException("Stub!");
    }

    public CaptureRequest getRequest() {
        throw new RuntimeException("Stub!");
    }

    public static final class Key<T> {
        private Key() {
            throw new RuntimeException("Stub!");
        }
    }
}
