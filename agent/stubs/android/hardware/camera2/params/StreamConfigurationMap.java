package android.hardware.camera2.params;

import android.util.Size;

public final class StreamConfigurationMap {
    private StreamConfigurationMap() {
        throw new RuntimeException("Stub!");
    }

    public Size[] getOutputSizes(int format) {
        throw new RuntimeException("Stub!");
    }
}
