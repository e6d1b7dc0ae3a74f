package android.hardware.camera2;

import android.hardware.camera2.params.StreamConfigurationMap;
import android.util.Range;

public final class CameraCharacteristics extends CameraMetadata<CameraCharacteristics.Key<?>> {
    public static final Key<Integer> LENS_FACING = null;
    public static final Key<Integer> LENS_INFO_FOCUS_DISTANCE_CALIBRATION = null;
    public static final Key<Float> LENS_INFO_MINIMUM_FOCUS_DISTANCE = null;
    public static final Key<int[]> REQUEST_AVAILABLE_CAPABILITIES = null;
    public static final Key<StreamConfigurationMap> SCALER_STREAM_CONFIGURATION_MAP = null;
    public static final Key<Range<Long>> SENSOR_INFO_EXPOSURE_TIME_RANGE = null;
    public static final Key<Range<Integer>> SENSOR_INFO_SENSITIVITY_RANGE = null;
    public static final Key<Integer> SENSOR_INFO_TIMESTAMP_SOURCE = null;

    private CameraCharacteristics() {
        throw new RuntimeException("Stub!");
    }

    public <T> T get(Key<T> key) {
        throw new RuntimeException("Stub!");
    }

    public static final class Key<T> {
        private Key() {
            throw new RuntimeException("Stub!");
        }
    }
}
