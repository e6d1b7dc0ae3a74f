package android.hardware.camera2;

public abstract class CameraMetadata<TKey> {
    public static final int CONTROL_AE_MODE_OFF = 0;
    public static final int CONTROL_AF_MODE_OFF = 0;
    public static final int CONTROL_AWB_MODE_AUTO = 1;
    public static final int CONTROL_MODE_AUTO = 1;
    public static final int FLASH_MODE_OFF = 0;
    public static final int LENS_FACING_BACK = 1;
    public static final int LENS_STATE_STATIONARY = 0;
    public static final int REQUEST_AVAILABLE_CAPABILITIES_MANUAL_SENSOR = 1;
    public static final int SENSOR_INFO_TIMESTAMP_SOURCE_REALTIME = 1;

    protected CameraMetadata() {
        throw new RuntimeException("Stub!");
    }
}
