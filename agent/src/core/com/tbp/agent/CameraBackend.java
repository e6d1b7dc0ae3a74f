package com.tbp.agent;

import java.nio.ByteBuffer;

/**
 * The camera below the protocol: Camera2 on a phone, the simulated phone's camera under the JVM.
 *
 * <p>The agent calls {@link #focus}, {@link #capture} and {@link #readClock} from its dispatcher
 * thread, never two camera operations at once; each call answers exactly once through its
 * {@link Result}, from any thread, possibly before the call returns. Times are nanoseconds on the
 * sensor's SENSOR_TIMESTAMP clock.
 */
public interface CameraBackend {

    /** What hello reports: the camera's fixed properties and the manual exposure in use. */
    final class Info {
        public final String model;
        public final String serial;
        public final double minFocusDiopters;
        public final int focusDistanceCalibration;
        public final String timestampSource;
        public final double exposureS;
        public final long iso;
        public final int imageWidth;
        public final int imageHeight;
        public final double minExposureS;
        public final double maxExposureS;
        public final long minIso;
        public final long maxIso;

        public Info(String model, String serial, double minFocusDiopters, int focusDistanceCalibration,
                    String timestampSource, double exposureS, long iso, int imageWidth, int imageHeight,
                    double minExposureS, double maxExposureS, long minIso, long maxIso) {
            this.model = model;
            this.serial = serial;
            this.minFocusDiopters = minFocusDiopters;
            this.focusDistanceCalibration = focusDistanceCalibration;
            this.timestampSource = timestampSource;
            this.exposureS = exposureS;
            this.iso = iso;
            this.imageWidth = imageWidth;
            this.imageHeight = imageHeight;
            this.minExposureS = minExposureS;
            this.maxExposureS = maxExposureS;
            this.minIso = minIso;
            this.maxIso = maxIso;
        }
    }

    /** The lens reported stationary: the LENS_FOCUS_DISTANCE of that result and its SENSOR_TIMESTAMP. */
    final class Focused {
        public final double diopters;
        public final long stationaryAtNs;

        public Focused(double diopters, long stationaryAtNs) {
            this.diopters = diopters;
            this.stationaryAtNs = stationaryAtNs;
        }
    }

    /** One still: the capture result's values and the JPEG, valid until {@link #release()}. */
    abstract class Still {
        public final long sensorTimestampNs;
        public final double exposureS;
        public final double focusDiopters;

        protected Still(long sensorTimestampNs, double exposureS, double focusDiopters) {
            this.sensorTimestampNs = sensorTimestampNs;
            this.exposureS = exposureS;
            this.focusDiopters = focusDiopters;
        }

        /** The JPEG bytes, position to limit. */
        public abstract ByteBuffer jpeg();

        /** Gives the image's buffer back to the camera (ImageReader's Image.close()); idempotent. */
        public abstract void release();
    }

    /** Exactly one of ok or failed, once. */
    interface Result<T> {
        void ok(T value);

        void failed(ErrorCode code, String message);
    }

    Info info();

    /** Move the lens to {@code diopters} (within [0, minFocusDiopters]); ok once it is stationary there. */
    void focus(double diopters, Result<Focused> result);

    /** One still at the current focus with this manual exposure (seconds) and sensitivity (ISO). */
    void capture(double exposureS, long iso, Result<Still> result);

    /** The sensor clock now. */
    void readClock(Result<Long> result);

    /** Stop the camera; an operation in flight may answer failed or not at all. Idempotent. */
    void close();
}
